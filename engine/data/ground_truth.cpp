#include "engine/data/ground_truth.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <exception>
#include <utility>

#include "core/error.hpp"
#include "core/hash.hpp"
#include "core/io.hpp"
#include "core/parallel.hpp"
#include "engine/util/progress.hpp"
#include "host/rasterize_labels.hpp"
#include "host/raywalk.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

namespace {

// Part of every cache key: bump when the content of a stored map changes for the same inputs.
constexpr uint32_t kGroundTruthVersion = 1;

void check_affine(const Pose& M, const char* what) {
  PS_CHECK(M.allFinite() && M(3, 0) == 0.0 && M(3, 1) == 0.0 && M(3, 2) == 0.0 && M(3, 3) == 1.0,
           "{}: expected a finite affine 4x4 transform with bottom row 0 0 0 1, got bottom row "
           "{} {} {} {}",
           what, M(3, 0), M(3, 1), M(3, 2), M(3, 3));
}

void check_grid(const GridSpec& grid) {
  PS_CHECK(grid.cell > 0 && grid.width() > 0 && grid.height() > 0 && grid.z_max > grid.z_min,
           "grid: expected cell > 0, x_max > x_min, y_max > y_min, z_max > z_min; got cell {}, x "
           "[{}, {}), y [{}, {}), z [{}, {})",
           grid.cell, grid.x_min, grid.x_max, grid.y_min, grid.y_max, grid.z_min, grid.z_max);
}

void check_index(const Sequence& sequence, size_t i) {
  PS_CHECK(i < sequence.size(), "scan index {} is out of range: sequence {} has {} scans", i,
           sequence_name(sequence.id()), sequence.size());
}

// Appends the points of `scan` moved by M that the aggregation keeps (see aggregate_scans).
void append_kept_points(const Scan& scan, const Pose& M, bool keep_moving, const ClassTable& table,
                        const CropRegion& crop, LabelledPoints& out) {
  const Eigen::Matrix3d linear = M.topLeftCorner<3, 3>();
  const Eigen::Vector3d offset = M.topRightCorner<3, 1>();
  out.points.reserve(out.points.size() + scan.points.size());
  out.classes.reserve(out.classes.size() + scan.points.size());
  for (size_t i = 0; i < scan.points.size(); ++i) {
    const uint32_t label = scan.labels[i];
    if (!keep_moving && table.is_moving(label)) continue;
    const uint8_t k = table.class_of(label);
    if (k == kUnlabeled || table.gt_weight(k) <= 0) continue;
    const Point& p = scan.points[i];
    const Eigen::Vector3d q = linear * Eigen::Vector3d(p.x, p.y, p.z) + offset;
    if (!crop.contains(q.x(), q.y(), q.z())) continue;
    out.points.push_back(
        {static_cast<float>(q.x()), static_cast<float>(q.y()), static_cast<float>(q.z()), p.r});
    out.classes.push_back(k);
  }
}

void add_grid(Hasher& h, const GridSpec& grid) {
  for (double v : {grid.x_min, grid.x_max, grid.y_min, grid.y_max, grid.z_min, grid.z_max,
                   grid.cell, grid.voxel_z})
    h.add(v);
}

std::string kind_key(GroundTruthKind kind) {
  return fmt::format("gt-{}", to_string(kind));
}

}  // namespace

std::string_view to_string(GroundTruthKind kind) {
  return kind == GroundTruthKind::sparse ? "sparse" : "dense";
}

GroundTruthKind parse_ground_truth_kind(std::string_view name) {
  if (name == "sparse") return GroundTruthKind::sparse;
  if (name == "dense") return GroundTruthKind::dense;
  PS_FAIL("ground-truth mode '{}': expected sparse or dense", name);
}

void LabelledPoints::transform(const Pose& M) {
  check_affine(M, "LabelledPoints::transform");
  const Eigen::Matrix3d linear = M.topLeftCorner<3, 3>();
  const Eigen::Vector3d offset = M.topRightCorner<3, 1>();
  for (Point& p : points) {
    const Eigen::Vector3d q = linear * Eigen::Vector3d(p.x, p.y, p.z) + offset;
    p.x = static_cast<float>(q.x());
    p.y = static_cast<float>(q.y());
    p.z = static_cast<float>(q.z());
  }
}

CropRegion crop_region(const GridSpec& grid, const AugmentationBounds& bounds) {
  check_grid(grid);
  PS_CHECK(bounds.scale_min > 0 && bounds.scale_max >= bounds.scale_min,
           "augmentation bounds: expected 0 < scale_min <= scale_max, got [{}, {}]",
           bounds.scale_min, bounds.scale_max);
  PS_CHECK(bounds.translation_xy >= 0 && bounds.translation_z >= 0,
           "augmentation bounds: expected translation bounds >= 0, got xy {}, z {}",
           bounds.translation_xy, bounds.translation_z);
  double corner = 0.0;
  for (double x : {grid.x_min, grid.x_max})
    for (double y : {grid.y_min, grid.y_max}) corner = std::max(corner, std::hypot(x, y));
  const double slack = grid.cell;
  CropRegion crop;
  crop.radius_xy = (corner + bounds.translation_xy) / bounds.scale_min + slack;
  // z' = s z + t_z must reach [z_min, z_max): the extreme z come from the extreme s and t_z.
  const double low = grid.z_min - bounds.translation_z, high = grid.z_max + bounds.translation_z;
  crop.z_min = std::min(low / bounds.scale_min, low / bounds.scale_max) - slack;
  crop.z_max = std::max(high / bounds.scale_min, high / bounds.scale_max) + slack;
  return crop;
}

double max_horizontal_range(std::span<const Point> points) {
  double d = 0.0;
  for (const Point& p : points) d = std::max(d, std::hypot(double{p.x}, double{p.y}));
  return d;
}

std::vector<Eigen::Vector3d> sensor_positions(const Sequence& sequence) {
  std::vector<Eigen::Vector3d> positions;
  positions.reserve(sequence.size());
  for (size_t i = 0; i < sequence.size(); ++i)
    positions.push_back(sequence.pose(i).topRightCorner<3, 1>());
  return positions;
}

std::vector<size_t> select_dense_neighbours(const std::vector<Eigen::Vector3d>& sensor_positions,
                                            size_t t, double d, size_t max_scans) {
  PS_CHECK(t < sensor_positions.size(), "dense neighbours: scan index {} is out of range (0..{})",
           t, static_cast<int64_t>(sensor_positions.size()) - 1);
  PS_CHECK(std::isfinite(d) && d >= 0, "dense neighbours: expected a finite range d >= 0, got {}",
           d);
  PS_CHECK(max_scans >= 1, "dense neighbours: expected max_scans >= 1 (scan t itself), got {}",
           max_scans);
  const double limit = kDenseDistanceFactor * d;
  std::vector<std::pair<double, size_t>> candidates;  // (distance, index): sorts as the rule says
  for (size_t j = 0; j < sensor_positions.size(); ++j) {
    if (j == t) continue;
    const double distance = (sensor_positions[j] - sensor_positions[t]).norm();
    if (distance < limit) candidates.emplace_back(distance, j);
  }
  const size_t kept = std::min(candidates.size(), max_scans - 1);
  std::partial_sort(candidates.begin(), candidates.begin() + static_cast<std::ptrdiff_t>(kept),
                    candidates.end());
  std::vector<size_t> scans = {t};
  for (size_t k = 0; k < kept; ++k) scans.push_back(candidates[k].second);
  return scans;
}

std::vector<size_t> dense_neighbours(const Sequence& sequence, size_t t, size_t max_scans) {
  check_index(sequence, t);
  const Scan scan = sequence.load(t);
  return select_dense_neighbours(sensor_positions(sequence), t, max_horizontal_range(scan.points),
                                 max_scans);
}

LabelledPoints aggregate_scans(const Sequence& sequence, std::span<const size_t> scans,
                               const ClassTable& table, const CropRegion& crop,
                               const Pose& transform) {
  PS_CHECK(!scans.empty(), "aggregate_scans: expected at least the current scan, got no scans");
  for (size_t j : scans) check_index(sequence, j);
  check_affine(transform, "aggregate_scans transform");
  const size_t t = scans[0];
  std::vector<LabelledPoints> parts(scans.size());
  // An exception must not leave an OpenMP region: keep each one and rethrow the first after.
  std::vector<std::exception_ptr> errors(scans.size());
  parallel_for(static_cast<int64_t>(scans.size()), [&](int64_t k) {
    try {
      const size_t j = scans[static_cast<size_t>(k)];
      PS_CHECK(sequence.has_labels(j),
               "ground truth needs the labels of every scan it uses: {} is missing",
               sequence.label_path(j).string());
      const Scan scan = sequence.load(j);
      const Pose to_output = j == t ? transform : Pose(transform * sequence.relative(t, j));
      append_kept_points(scan, to_output, j == t, table, crop, parts[static_cast<size_t>(k)]);
    } catch (...) {
      errors[static_cast<size_t>(k)] = std::current_exception();
    }
  });
  for (const std::exception_ptr& error : errors)
    if (error) std::rethrow_exception(error);

  size_t total = 0;
  for (const LabelledPoints& part : parts) total += part.size();
  LabelledPoints set;
  set.points.reserve(total);
  set.classes.reserve(total);
  for (const LabelledPoints& part : parts) {
    set.points.insert(set.points.end(), part.points.begin(), part.points.end());
    set.classes.insert(set.classes.end(), part.classes.begin(), part.classes.end());
  }
  return set;
}

LabelledPoints dense_points(const Sequence& sequence, size_t t, const ClassTable& table,
                            const GridSpec& grid, const AugmentationBounds& bounds,
                            size_t max_scans, const Pose& transform) {
  const std::vector<size_t> scans = dense_neighbours(sequence, t, max_scans);
  return aggregate_scans(sequence, scans, table, crop_region(grid, bounds), transform);
}

Tensor<uint8_t> sparse_ground_truth(const Scan& scan, const ClassTable& table,
                                    const GridSpec& grid) {
  PS_CHECK(scan.labelled(), "sparse ground truth: the scan has {} points but no labels",
           scan.points.size());
  return rasterize_labels(scan.points, scan.labels, table, grid);
}

Tensor<uint8_t> dense_ground_truth(const Sequence& sequence, size_t t, const ClassTable& table,
                                   const GridSpec& grid, size_t max_scans, const Pose& transform) {
  const LabelledPoints set =
      dense_points(sequence, t, table, grid, AugmentationBounds::none(), max_scans, transform);
  return rasterize_classes(set.points, set.classes, table, grid);
}

std::vector<char> encode_labelled_points(const LabelledPoints& set) {
  PS_CHECK(set.classes.size() == set.points.size(), "labelled points: {} points but {} class ids",
           set.points.size(), set.classes.size());
  const uint64_t n = set.size();
  std::vector<char> bytes(sizeof n + n * (sizeof(Point) + 1));
  std::memcpy(bytes.data(), &n, sizeof n);
  if (n > 0) {
    std::memcpy(bytes.data() + sizeof n, set.points.data(), n * sizeof(Point));
    std::memcpy(bytes.data() + sizeof n + n * sizeof(Point), set.classes.data(), n);
  }
  return bytes;
}

std::optional<LabelledPoints> decode_labelled_points(std::span<const char> bytes) {
  uint64_t n = 0;
  if (bytes.size() < sizeof n) return std::nullopt;
  std::memcpy(&n, bytes.data(), sizeof n);
  if (n > bytes.size() / (sizeof(Point) + 1) || bytes.size() != sizeof n + n * (sizeof(Point) + 1))
    return std::nullopt;
  LabelledPoints set;
  set.points.resize(n);
  set.classes.resize(n);
  if (n > 0) {
    std::memcpy(set.points.data(), bytes.data() + sizeof n, n * sizeof(Point));
    std::memcpy(set.classes.data(), bytes.data() + sizeof n + n * sizeof(Point), n);
  }
  for (uint8_t k : set.classes)
    if (k >= kNumClassIds) return std::nullopt;
  return set;
}

GroundTruthBuilder::GroundTruthBuilder(Sequence sequence, ClassTable table,
                                       GroundTruthSettings settings, std::optional<Cache> cache)
    : sequence_(std::move(sequence)),
      table_(std::move(table)),
      settings_(settings),
      cache_(std::move(cache)) {
  check_grid(settings_.grid);
  PS_CHECK(settings_.max_scans >= 1, "ground truth: expected max_scans >= 1, got {}",
           settings_.max_scans);
  crop_region(settings_.grid, settings_.augmentation);  // validates the bounds
  std::error_code ec;
  const fs::path canonical = fs::canonical(sequence_.dir(), ec);
  PS_CHECK(!ec, "{}: cannot resolve the sequence directory: {}", sequence_.dir().string(),
           ec.message());
  sequence_path_ = canonical.string();
}

CacheKey GroundTruthBuilder::make_key(size_t i, std::string kind, uint64_t settings,
                                      uint64_t inputs) const {
  return CacheKey{sequence_path_, sequence_.frame(i), std::move(kind), settings, inputs};
}

uint64_t GroundTruthBuilder::dense_inputs_hash(const std::vector<size_t>& scans) const {
  Hasher inputs;
  hash_file_stamp(inputs, sequence_.dir() / "poses.txt");
  hash_file_stamp(inputs, sequence_.dir() / "calib.txt");
  for (size_t j : scans) {
    inputs.add(sequence_.frame(j));
    hash_file_stamp(inputs, sequence_.scan_path(j));
    hash_file_stamp(inputs, sequence_.label_path(j));
  }
  return inputs.digest();
}

CacheKey GroundTruthBuilder::key(size_t i, GroundTruthKind kind) const {
  check_index(sequence_, i);
  Hasher settings;
  settings.add(kGroundTruthVersion);
  settings.add(kind_key(kind));
  add_grid(settings, settings_.grid);
  settings.add(table_.fingerprint());
  sequence_.input().add_to(settings);
  if (kind == GroundTruthKind::sparse) {
    Hasher inputs;
    hash_file_stamp(inputs, sequence_.scan_path(i));
    hash_file_stamp(inputs, sequence_.label_path(i));
    return make_key(i, kind_key(kind), settings.digest(), inputs.digest());
  }
  settings.add(static_cast<uint64_t>(settings_.max_scans));
  settings.add(kDenseDistanceFactor);
  return make_key(i, kind_key(kind), settings.digest(), dense_inputs_hash(neighbours(i)));
}

namespace {
// Observability and occupancy of a scan: the key covers the grid and the scan file.
CacheKey ray_map_key(const Sequence& seq, const std::string& path, size_t i, const std::string& kind,
                     const GridSpec& grid) {
  Hasher settings;
  settings.add(kGroundTruthVersion);
  settings.add(std::string_view(kind));
  add_grid(settings, grid);
  seq.input().add_to(settings);
  Hasher inputs;
  hash_file_stamp(inputs, seq.scan_path(i));
  return CacheKey{path, seq.frame(i), kind, settings.digest(), inputs.digest()};
}

template <class T, class Compute>
Tensor<T> cached_map(const std::optional<Cache>& cache, const CacheKey& key, bool* from_cache, Compute&& compute) {
  if (cache) {
    if (std::optional<Tensor<T>> hit = cache->load<T>(key)) {
      if (from_cache) *from_cache = true;
      return std::move(*hit);
    }
  }
  if (from_cache) *from_cache = false;
  Tensor<T> map = compute();
  if (cache) cache->store(key, map);
  return map;
}
}  // namespace

Tensor<uint32_t> GroundTruthBuilder::observability(size_t i, bool* from_cache) const {
  check_index(sequence_, i);
  const CacheKey key = ray_map_key(sequence_, sequence_path_, i, "observability", settings_.grid);
  return cached_map<uint32_t>(cache_, key, from_cache, [&] {
    const Scan scan = sequence_.load(i);
    return host::observability_map(host::observability_2d(scan.points, Eigen::Vector3d::Zero(), settings_.grid));
  });
}

Tensor<float> GroundTruthBuilder::occupancy(size_t i, bool* from_cache) const {
  check_index(sequence_, i);
  const CacheKey key = ray_map_key(sequence_, sequence_path_, i, "occupancy", settings_.grid);
  return cached_map<float>(cache_, key, from_cache, [&] {
    const Scan scan = sequence_.load(i);
    return host::occupancy_probability(host::occupancy_counts_3d(scan.points, Eigen::Vector3d::Zero(), settings_.grid));
  });
}

std::vector<size_t> GroundTruthBuilder::neighbours(size_t i) const {
  check_index(sequence_, i);
  if (!cache_) return dense_neighbours(sequence_, i, settings_.max_scans);
  Hasher settings;
  settings.add(kGroundTruthVersion);
  settings.add(static_cast<uint64_t>(settings_.max_scans));
  settings.add(kDenseDistanceFactor);
  sequence_.input().add_to(settings);
  // Indices refer to the sequence's scan list, so the list is an input like the files.
  Hasher inputs;
  hash_file_stamp(inputs, sequence_.scan_path(i));
  hash_file_stamp(inputs, sequence_.dir() / "poses.txt");
  hash_file_stamp(inputs, sequence_.dir() / "calib.txt");
  inputs.add(static_cast<uint64_t>(sequence_.size()));
  for (size_t j = 0; j < sequence_.size(); ++j) inputs.add(sequence_.frame(j));
  const CacheKey key = make_key(i, "dense-neighbours", settings.digest(), inputs.digest());

  if (const std::optional<Tensor<int64_t>> stored = cache_->load<int64_t>(key)) {
    const bool valid =
        stored->rank() == 1 && stored->numel() >= 1 &&
        static_cast<size_t>(stored->numel()) <= settings_.max_scans &&
        (*stored)[0] == static_cast<int64_t>(i) &&
        std::all_of(stored->data(), stored->data() + stored->numel(),
                    [&](int64_t j) { return j >= 0 && static_cast<size_t>(j) < sequence_.size(); });
    if (valid) return std::vector<size_t>(stored->data(), stored->data() + stored->numel());
  }
  const std::vector<size_t> scans = dense_neighbours(sequence_, i, settings_.max_scans);
  Tensor<int64_t> stored({static_cast<int64_t>(scans.size())});
  for (size_t k = 0; k < scans.size(); ++k)
    stored[static_cast<int64_t>(k)] = static_cast<int64_t>(scans[k]);
  cache_->store(key, stored);
  return scans;
}

Tensor<uint8_t> GroundTruthBuilder::compute(size_t i, GroundTruthKind kind) const {
  if (kind == GroundTruthKind::sparse) {
    PS_CHECK(sequence_.has_labels(i), "sparse ground truth needs labels: {} is missing",
             sequence_.label_path(i).string());
    return sparse_ground_truth(sequence_.load(i), table_, settings_.grid);
  }
  const LabelledPoints set = aggregate_scans(
      sequence_, neighbours(i), table_, crop_region(settings_.grid, AugmentationBounds::none()));
  return rasterize_classes(set.points, set.classes, table_, settings_.grid);
}

Tensor<uint8_t> GroundTruthBuilder::map(size_t i, GroundTruthKind kind, bool* from_cache) const {
  check_index(sequence_, i);
  if (from_cache) *from_cache = false;
  if (!cache_) return compute(i, kind);
  const CacheKey map_key = key(i, kind);
  if (std::optional<Tensor<uint8_t>> stored = cache_->load<uint8_t>(map_key);
      stored && stored->shape() == Shape{settings_.grid.height(), settings_.grid.width()}) {
    if (from_cache) *from_cache = true;
    return std::move(*stored);
  }
  Tensor<uint8_t> computed = compute(i, kind);
  cache_->store(map_key, computed);
  return computed;
}

LabelledPoints GroundTruthBuilder::dense_points(size_t i) const {
  check_index(sequence_, i);
  const CropRegion crop = crop_region(settings_.grid, settings_.augmentation);
  if (!cache_ || !settings_.cache_dense_points)
    return aggregate_scans(sequence_, neighbours(i), table_, crop);
  const std::vector<size_t> scans = neighbours(i);
  Hasher settings;
  settings.add(kGroundTruthVersion);
  settings.add(static_cast<uint64_t>(settings_.max_scans));
  settings.add(kDenseDistanceFactor);
  settings.add(table_.fingerprint());
  sequence_.input().add_to(settings);
  for (double v : {crop.radius_xy, crop.z_min, crop.z_max}) settings.add(v);
  const CacheKey key = make_key(i, "gt-dense-points", settings.digest(), dense_inputs_hash(scans));
  if (const std::optional<std::vector<char>> bytes = cache_->load_bytes(key))
    if (std::optional<LabelledPoints> set = decode_labelled_points(*bytes)) return std::move(*set);
  LabelledPoints set = aggregate_scans(sequence_, scans, table_, crop);
  cache_->store_bytes(key, encode_labelled_points(set));
  return set;
}

GroundTruthBuilder::BuildCounts GroundTruthBuilder::build_all(GroundTruthKind kind,
                                                              bool show_progress) const {
  PS_CHECK(cache_.has_value(),
           "building the ground-truth cache of sequence {} needs a cache directory",
           sequence_name(sequence_.id()));
  cache_->remove_stale_temporaries(sequence_path_);
  BuildCounts counts;
  std::optional<Progress> progress;
  if (show_progress)
    progress.emplace(
        fmt::format("gt {} sequence {}", to_string(kind), sequence_name(sequence_.id())),
        static_cast<int64_t>(sequence_.size()), "scans");
  for (size_t i = 0; i < sequence_.size(); ++i) {
    bool from_cache = false;
    map(i, kind, &from_cache);
    ++(from_cache ? counts.cached : counts.computed);
    if (progress)
      progress->update(static_cast<int64_t>(i + 1),
                       fmt::format("computed {}, cached {}", counts.computed, counts.cached));
  }
  if (progress) progress->finish();
  return counts;
}

}  // namespace pillarseg
