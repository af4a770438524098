// Ground truth (DESIGN.md section 1): sparse and dense top-view class maps, (H, W) uint8,
// row iy, column ix, class ids 0..12 (0 = unlabeled).
// - Sparse: the sparse rule (host/rasterize_labels) on scan t's labelled points.
// - Dense: the scans whose sensor positions lie within 2 d of scan t's (d = the largest
//   horizontal distance of a point of scan t from its sensor), at most 40 counting t, nearest
//   first, are brought into scan t's frame; their static points plus scan t's moving points
//   go through the same rule.
// The pieces are exposed so that augmented training can move the aggregated point set with
// the augmentation and rasterise it again: a 4x4 affine `transform` (AugmentTransform::
// as_matrix()) composes on the left of every relative pose, p -> transform * inv(T_t) T_j p,
// for scan t itself as for its neighbours. GroundTruthBuilder serves the maps through the
// on-disk cache (engine/data/cache.hpp); `pillarseg gt` is engine/cli/cmd_gt.cpp.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/classes.hpp"
#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/tensor.hpp"
#include "engine/data/cache.hpp"
#include "engine/data/semantickitti.hpp"

namespace pillarseg {

enum class GroundTruthKind { sparse, dense };
std::string_view to_string(GroundTruthKind kind);
// "sparse" or "dense"; anything else is an Error naming the value.
GroundTruthKind parse_ground_truth_kind(std::string_view name);

inline constexpr size_t kDenseMaxScans = 40;         // scans aggregated, counting scan t
inline constexpr double kDenseDistanceFactor = 2.0;  // neighbours within 2 d of scan t

// Labelled points already mapped to classes: points (N) and class ids (N), 1..12 for the
// aggregated sets (weight-0 points are dropped: they cannot change a map).
struct LabelledPoints {
  std::vector<Point> points;
  std::vector<uint8_t> classes;

  size_t size() const { return points.size(); }
  // p -> M p for the affine 4x4 M (bottom row 0 0 0 1), in double, stored as float.
  void transform(const Pose& M);
};

// Bounds on the augmentation that may still be applied to an aggregated set: a flip and a
// rotation about z (which keep |p_xy|), a uniform scale in [scale_min, scale_max] and a
// translation with |t_xy| <= translation_xy, |t_z| <= translation_z. The defaults are those of
// the default training augmentation (translation off); with translation on, pass a bound such
// as 4 sigma (points beyond it are lost with probability ~1e-4). none(): no later movement.
struct AugmentationBounds {
  double scale_min = 0.95, scale_max = 1.05;
  double translation_xy = 0.0, translation_z = 0.0;
  static AugmentationBounds none() { return {1.0, 1.0, 0.0, 0.0}; }
};

// The region of points that can still land in the grid volume after any augmentation within
// the bounds: q = s R p + t lies in the grid only if |q_xy| <= c (c: the distance of the
// grid's farthest corner from the sensor), so |p_xy| <= (c + translation_xy) / scale_min; z
// likewise. One cell of slack on each bound absorbs float rounding.
struct CropRegion {
  double radius_xy = 0.0;
  double z_min = 0.0, z_max = 0.0;
  bool contains(double x, double y, double z) const {
    return x * x + y * y <= radius_xy * radius_xy && z >= z_min && z <= z_max;
  }
};
CropRegion crop_region(const GridSpec& grid, const AugmentationBounds& bounds);

// d of the dense rule: max over points of sqrt(x^2 + y^2) (0 for an empty scan). points (N).
double max_horizontal_range(std::span<const Point> points);

// Translation of pose(i) for every scan of the sequence (needs poses.txt and calib.txt).
std::vector<Eigen::Vector3d> sensor_positions(const Sequence& sequence);

// The scans aggregated for scan t: t first, then every j with |p_j - p_t| < 2 d, nearest
// first (ties: lower index), at most max_scans in all. t comes first even when other scans
// share its position, since its moving points are part of the map.
std::vector<size_t> select_dense_neighbours(const std::vector<Eigen::Vector3d>& sensor_positions,
                                            size_t t, double d, size_t max_scans = kDenseMaxScans);

// select_dense_neighbours for scan t of the sequence (reads scan t's .bin for d).
std::vector<size_t> dense_neighbours(const Sequence& sequence, size_t t,
                                     size_t max_scans = kDenseMaxScans);

// The points of `scans` (indices into the sequence; scans[0] is the current scan t) in scan
// t's frame moved by `transform`, kept when inside `crop` (tested after the move) and of
// positive ground-truth weight; moving points (ClassTable::is_moving, raw ids 252-259) only
// from scan t. Scans are loaded in parallel; the order is scan by scan as listed, points in
// file order, whatever the thread count. Every scan needs labels.
LabelledPoints aggregate_scans(const Sequence& sequence, std::span<const size_t> scans,
                               const ClassTable& table, const CropRegion& crop,
                               const Pose& transform = Pose::Identity());

// The dense aggregated set of scan t cropped for `bounds`: aggregate_scans over
// dense_neighbours, what augmented training re-rasterises after moving it.
LabelledPoints dense_points(const Sequence& sequence, size_t t, const ClassTable& table,
                            const GridSpec& grid, const AugmentationBounds& bounds,
                            size_t max_scans = kDenseMaxScans,
                            const Pose& transform = Pose::Identity());

// Sparse map of a labelled scan (points already moved by any augmentation). Returns (H, W).
Tensor<uint8_t> sparse_ground_truth(const Scan& scan, const ClassTable& table,
                                    const GridSpec& grid);

// Dense map of scan t, every aggregated scan moved by `transform`. Returns (H, W).
Tensor<uint8_t> dense_ground_truth(const Sequence& sequence, size_t t, const ClassTable& table,
                                   const GridSpec& grid, size_t max_scans = kDenseMaxScans,
                                   const Pose& transform = Pose::Identity());

// Serialised form of a LabelledPoints for the cache: u64 N | N x 16-byte Point | N class ids.
std::vector<char> encode_labelled_points(const LabelledPoints& set);
// nullopt when the bytes are not such a record (sizes disagree, a class id above 12).
std::optional<LabelledPoints> decode_labelled_points(std::span<const char> bytes);

struct GroundTruthSettings {
  GridSpec grid;
  size_t max_scans = kDenseMaxScans;
  AugmentationBounds augmentation;  // crop of GroundTruthBuilder::dense_points
  // Dense point sets take tens of MB a scan on disk, so caching them is opt-in.
  bool cache_dense_points = false;
};

// Maps of one sequence through the on-disk cache: a valid entry is read, a miss is computed
// and stored. Used by `pillarseg gt` and by training.
class GroundTruthBuilder {
 public:
  // Without a cache every call computes afresh.
  GroundTruthBuilder(Sequence sequence, ClassTable table, GroundTruthSettings settings,
                     std::optional<Cache> cache);

  const Sequence& sequence() const { return sequence_; }
  const ClassTable& table() const { return table_; }
  const GroundTruthSettings& settings() const { return settings_; }

  // (H, W) map of the sequence's i-th scan; *from_cache (if given) tells whether it was read.
  Tensor<uint8_t> map(size_t i, GroundTruthKind kind, bool* from_cache = nullptr) const;
  // The 2D observability counts (H, W) and the 3D occupancy probability (Z, H, W) of scan i
  // in its own frame (the sensor at the origin, no augmentation), through the cache.
  Tensor<uint32_t> observability(size_t i, bool* from_cache = nullptr) const;
  Tensor<float> occupancy(size_t i, bool* from_cache = nullptr) const;
  // dense_neighbours of scan i (cached: a lookup then needs no scan read).
  std::vector<size_t> neighbours(size_t i) const;
  // dense_points of scan i cropped for settings().augmentation, in scan i's frame.
  LabelledPoints dense_points(size_t i) const;
  // Key of scan i's map. The dense key covers the neighbours' files, poses.txt and calib.txt.
  CacheKey key(size_t i, GroundTruthKind kind) const;

  struct BuildCounts {
    size_t computed = 0, cached = 0;
  };
  // Puts every scan's map in the cache (requires one), with a progress display on stderr.
  BuildCounts build_all(GroundTruthKind kind, bool show_progress = true) const;

 private:
  Tensor<uint8_t> compute(size_t i, GroundTruthKind kind) const;
  CacheKey make_key(size_t i, std::string kind, uint64_t settings, uint64_t inputs) const;
  uint64_t dense_inputs_hash(const std::vector<size_t>& scans) const;

  Sequence sequence_;
  ClassTable table_;
  GroundTruthSettings settings_;
  std::optional<Cache> cache_;
  std::string sequence_path_;  // canonical, for cache keys
};

}  // namespace pillarseg
