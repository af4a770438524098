// Ground-truth timings on a synthetic 121,600-point labelled scan (64 beams x 1900 azimuths
// ray-cast against a ground plane, two building rows, parked and moving cars and a vegetation
// backdrop, seeded range noise):
// - sparse rule on one core at the default 1000 x 500 grid, next to the same rule on a full
//   (cells x 13) count array, the peer it replaces;
// - dense ground truth of a 40-scan sequence (1 m apart, written once to a temporary
//   directory): neighbour selection, loading, transforming, rasterising; and its parts;
// - a cache hit of a dense map.
// Rates are input points per second.
#include <benchmark/benchmark.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <numbers>
#include <vector>

#include "core/classes.hpp"
#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "engine/data/cache.hpp"
#include "engine/data/ground_truth.hpp"
#include "engine/data/semantickitti.hpp"
#include "host/rasterize_labels.hpp"

using namespace pillarseg;
namespace fs = std::filesystem;

namespace {

constexpr int kBeams = 64;
constexpr int kAzimuths = 1900;
constexpr int kScans = 40;
constexpr double kSensorHeight = 1.73;
constexpr double kScanSpacing = 1.0;  // metres driven between scans

struct Box {  // an axis-aligned obstacle in the world, labelled `label`
  Eigen::Vector3d lo, hi;
  uint32_t label;
};

// Street scene in world coordinates (the ego drives along +x at y = 0).
const std::vector<Box>& scene_boxes() {
  static const std::vector<Box> boxes = [] {
    std::vector<Box> b;
    for (int i = 0; i < 12; ++i) {  // parked cars on both sides
      const double x = -30.0 + 9.0 * i;
      b.push_back({{x, 3.6, -kSensorHeight}, {x + 4.2, 5.4, -kSensorHeight + 1.5}, 10});
      b.push_back({{x + 3.0, -5.4, -kSensorHeight}, {x + 7.2, -3.6, -kSensorHeight + 1.5}, 10});
    }
    b.push_back({{12.0, -2.8, -kSensorHeight}, {16.5, -1.0, -kSensorHeight + 1.6}, 252});  // moving
    b.push_back({{25.0, 1.0, -kSensorHeight}, {29.5, 2.8, -kSensorHeight + 1.6}, 252});
    b.push_back({{8.0, 6.5, -kSensorHeight}, {8.6, 7.1, -kSensorHeight + 1.8}, 30});  // person
    return b;
  }();
  return boxes;
}

// Distance along dir from origin to the box, or infinity (slab method).
double hit_box(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, const Box& box) {
  double t0 = 0.0, t1 = INFINITY;
  for (int a = 0; a < 3; ++a) {
    const double inv = 1.0 / dir[a];
    double near = (box.lo[a] - origin[a]) * inv, far = (box.hi[a] - origin[a]) * inv;
    if (near > far) std::swap(near, far);
    t0 = std::max(t0, near);
    t1 = std::min(t1, far);
  }
  return t0 <= t1 ? t0 : INFINITY;
}

// One scan from a sensor at world (sensor_x, 0), points in its LiDAR frame: every ray returns
// (ground, building walls at |y| = 12, boxes, or the vegetation cylinder at 70 m).
void make_scan(double sensor_x, uint64_t seed, std::vector<Point>& points,
               std::vector<uint32_t>& labels) {
  Rng rng(seed);
  points.clear(), labels.clear();
  points.reserve(kBeams * kAzimuths), labels.reserve(kBeams * kAzimuths);
  const Eigen::Vector3d origin(sensor_x, 0.0, 0.0);
  for (int beam = 0; beam < kBeams; ++beam) {
    const double elevation = (2.0 - 26.8 * beam / (kBeams - 1)) * std::numbers::pi / 180.0;
    for (int a = 0; a < kAzimuths; ++a) {
      const double azimuth = 2.0 * std::numbers::pi * a / kAzimuths;
      const Eigen::Vector3d dir(std::cos(elevation) * std::cos(azimuth),
                                std::cos(elevation) * std::sin(azimuth), std::sin(elevation));
      double range = 70.0 / std::cos(elevation);  // vegetation backdrop
      uint32_t label = 70;
      if (dir.z() < 0 && kSensorHeight / -dir.z() < range) {
        range = kSensorHeight / -dir.z();
        const double y = std::abs(range * dir.y());
        label = y < 3.5 ? 40 : (y < 6.0 ? 48 : 72);  // road, sidewalk, terrain
      }
      if (std::abs(dir.y()) > 1e-9 && 12.0 / std::abs(dir.y()) < range) {
        range = 12.0 / std::abs(dir.y());
        label = 50;
      }
      for (const Box& box : scene_boxes()) {
        const double t = hit_box(origin, dir, box);
        if (t < range) range = t, label = box.label;
      }
      range += rng.normal(0.0, 0.02);
      if (rng.bernoulli(0.03)) label = 0;  // unlabeled returns
      points.push_back({static_cast<float>(range * dir.x()), static_cast<float>(range * dir.y()),
                        static_cast<float>(range * dir.z()), static_cast<float>(rng.uniform())});
      labels.push_back(label);
    }
  }
}

struct SingleScan {
  std::vector<Point> points;
  std::vector<uint32_t> labels;
  SingleScan() { make_scan(0.0, 1, points, labels); }
};
const SingleScan& single_scan() {
  static const SingleScan scan;
  return scan;
}

// A 40-scan sequence in SemanticKITTI layout under the system temporary directory, removed
// at exit.
class SyntheticSequence {
 public:
  SyntheticSequence()
      : root_(fs::temp_directory_path() / ("pillarseg_bench_gt_" + std::to_string(::getpid()))) {
    const fs::path dir = root_ / "sequences" / "00";
    Calib calib;
    for (auto& P : calib.P) P = Eigen::Matrix<double, 3, 4>::Identity();
    calib.Tr.topLeftCorner<3, 3>() << 0, -1, 0, 0, 0, -1, 1, 0, 0;  // KITTI's axis permutation
    write_calib(dir / "calib.txt", calib);
    std::vector<Pose> cam0;
    std::vector<Point> points;
    std::vector<uint32_t> labels;
    for (int j = 0; j < kScans; ++j) {
      Pose lidar = Pose::Identity();
      lidar(0, 3) = kScanSpacing * j;
      cam0.push_back(calib.Tr * lidar * calib.Tr.inverse());
      make_scan(kScanSpacing * j, 100 + static_cast<uint64_t>(j), points, labels);
      write_bin(dir / "velodyne" / fmt::format("{:06}.bin", j), points);
      write_labels(dir / "labels" / fmt::format("{:06}.label", j), labels);
    }
    write_poses(dir / "poses.txt", cam0);
  }
  ~SyntheticSequence() {
    std::error_code ec;
    fs::remove_all(root_, ec);
  }
  const fs::path& root() const { return root_; }

 private:
  fs::path root_;
};
const SyntheticSequence& synthetic_sequence() {
  static const SyntheticSequence sequence;
  return sequence;
}

// The peer: the sparse rule on a (cells x 13) count array cleared every call.
Tensor<uint8_t> rasterize_full_count_array(const std::vector<Point>& points,
                                           const std::vector<uint32_t>& labels,
                                           const ClassTable& table, const GridSpec& grid) {
  std::vector<uint32_t> counts(static_cast<size_t>(grid.cells()) * kNumClassIds, 0);
  for (size_t i = 0; i < points.size(); ++i) {
    const Point& p = points[i];
    if (!grid.contains(p.x, p.y, p.z)) continue;
    ++counts[static_cast<size_t>(grid.cell_index(p.x, p.y)) * kNumClassIds +
             table.class_of(labels[i])];
  }
  Tensor<uint8_t> map({grid.height(), grid.width()});
  for (int64_t c = 0; c < grid.cells(); ++c) {
    int64_t best = 0;
    for (int k = 1; k < kNumClassIds; ++k) {
      const int64_t score =
          int64_t{table.gt_weight(k)} * counts[static_cast<size_t>(c) * kNumClassIds + k];
      if (score > best) best = score, map[c] = static_cast<uint8_t>(k);
    }
  }
  return map;
}

void set_points_rate(benchmark::State& state, double points) {
  state.counters["points/s"] =
      benchmark::Counter(points, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["points"] = points;
}

void BM_SparseGroundTruth(benchmark::State& state) {
  const SingleScan& scan = single_scan();
  const ClassTable table = ClassTable::defaults();
  const GridSpec grid;
  for (auto _ : state)
    benchmark::DoNotOptimize(rasterize_labels(scan.points, scan.labels, table, grid));
  set_points_rate(state, static_cast<double>(scan.points.size()));
}
BENCHMARK(BM_SparseGroundTruth)->Unit(benchmark::kMillisecond);

void BM_SparseFullCountArray(benchmark::State& state) {
  const SingleScan& scan = single_scan();
  const ClassTable table = ClassTable::defaults();
  const GridSpec grid;
  if (rasterize_full_count_array(scan.points, scan.labels, table, grid).values() !=
      rasterize_labels(scan.points, scan.labels, table, grid).values())
    state.SkipWithError("the full-count-array peer disagrees with rasterize_labels");
  for (auto _ : state)
    benchmark::DoNotOptimize(rasterize_full_count_array(scan.points, scan.labels, table, grid));
  set_points_rate(state, static_cast<double>(scan.points.size()));
}
BENCHMARK(BM_SparseFullCountArray)->Unit(benchmark::kMillisecond);

// Dense ground truth of the middle scan (all 40 scans are within 2 d): argument = threads.
void BM_DenseGroundTruth(benchmark::State& state) {
  const Sequence sequence(synthetic_sequence().root(), 0);
  const ClassTable table = ClassTable::defaults();
  const GridSpec grid;
  const int saved = num_threads();
  set_num_threads(static_cast<int>(state.range(0)));
  const size_t t = kScans / 2;
  if (dense_neighbours(sequence, t).size() != kScans)
    state.SkipWithError("expected 40 aggregated scans");
  for (auto _ : state) benchmark::DoNotOptimize(dense_ground_truth(sequence, t, table, grid));
  set_num_threads(saved);
  set_points_rate(state, static_cast<double>(kScans) * kBeams * kAzimuths);
}
BENCHMARK(BM_DenseGroundTruth)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond)->UseRealTime();

// The aggregation alone (load, transform, filter 40 scans), cropped for the default
// augmentation: what augmented dense training redoes or reads from the cache.
void BM_DenseAggregate(benchmark::State& state) {
  const Sequence sequence(synthetic_sequence().root(), 0);
  const ClassTable table = ClassTable::defaults();
  const GridSpec grid;
  const int saved = num_threads();
  set_num_threads(static_cast<int>(state.range(0)));
  size_t kept = 0;
  for (auto _ : state) {
    const LabelledPoints set =
        dense_points(sequence, kScans / 2, table, grid, AugmentationBounds{});
    kept = set.size();
  }
  set_num_threads(saved);
  set_points_rate(state, static_cast<double>(kScans) * kBeams * kAzimuths);
  state.counters["kept"] = static_cast<double>(kept);
}
BENCHMARK(BM_DenseAggregate)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond)->UseRealTime();

// The sparse rule on the aggregated set (one core).
void BM_DenseRasterize(benchmark::State& state) {
  const Sequence sequence(synthetic_sequence().root(), 0);
  const ClassTable table = ClassTable::defaults();
  const GridSpec grid;
  const LabelledPoints set =
      dense_points(sequence, kScans / 2, table, grid, AugmentationBounds::none());
  for (auto _ : state)
    benchmark::DoNotOptimize(rasterize_classes(set.points, set.classes, table, grid));
  set_points_rate(state, static_cast<double>(set.size()));
}
BENCHMARK(BM_DenseRasterize)->Unit(benchmark::kMillisecond);

// A cache hit: read and verify one stored (500, 1000) map.
void BM_CacheHitDenseMap(benchmark::State& state) {
  const Cache cache(synthetic_sequence().root() / "cache");
  const CacheKey key{"/bench/sequences/00", 20, "gt-dense", 1, 2};
  cache.store(key, Tensor<uint8_t>({500, 1000}, 5));
  for (auto _ : state) benchmark::DoNotOptimize(cache.load<uint8_t>(key));
  state.counters["MB/s"] =
      benchmark::Counter(500.0 * 1000.0 / 1e6, benchmark::Counter::kIsIterationInvariantRate);
}
BENCHMARK(BM_CacheHitDenseMap)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
