// SemanticKITTI files: .bin point clouds, .label files, poses.txt, calib.txt, and the
// sequence layout ROOT/sequences/SS/{velodyne/NNNNNN.bin, labels/NNNNNN.label, poses.txt,
// calib.txt}. Readers validate and throw pillarseg::Error naming the file and the problem;
// writers are atomic.
#pragma once

#include <array>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "core/eigen.hpp"
#include "core/point.hpp"
#include "engine/data/input_mapping.hpp"

namespace pillarseg {

// Reads a KITTI .bin file (read_points with PointFormat::Kitti): size must be a multiple of 16. Points with a non-finite coordinate or
// reflectance are dropped (counted in Scan::dropped_nonfinite, logged as a warning); when
// label_path is given, the label count must equal the record count of the .bin file and
// the labels of dropped points are dropped with them.
Scan read_scan(const std::filesystem::path& bin_path,
               const std::optional<std::filesystem::path>& label_path = std::nullopt);
std::vector<uint32_t> read_labels(const std::filesystem::path& label_path);

void write_bin(const std::filesystem::path& path, const std::vector<Point>& points);
void write_labels(const std::filesystem::path& path, const std::vector<uint32_t>& labels);

// poses.txt: one line per scan, 12 numbers, the row-major 3x4 pose of cam0 (as 4x4).
std::vector<Pose> read_poses(const std::filesystem::path& path);
void write_poses(const std::filesystem::path& path, const std::vector<Pose>& poses);

// calib.txt: lines "P0:".."P3:" and "Tr:" with 12 numbers each; Tr maps LiDAR -> cam0.
struct Calib {
  std::array<Eigen::Matrix<double, 3, 4>, 4> P;  // projection matrices (unused by the engine)
  Pose Tr = Pose::Identity();
};
Calib read_calib(const std::filesystem::path& path);
void write_calib(const std::filesystem::path& path, const Calib& calib);

// LiDAR-frame poses T_i = inv(Tr) * pose_i * Tr.
std::vector<Pose> lidar_poses(const std::vector<Pose>& cam0_poses, const Calib& calib);

// One sequence directory ROOT/sequences/SS. Scan indices are those of the point files found
// (velodyne/NNNNNN.bin, or .pcd, .ply, .npy, .pcd.bin: engine/data/point_formats.hpp), sorted;
// labels and poses are optional (a test-only sequence has neither). With an input mapping, the
// scans and poses are in the model's frame: load() maps the points, pose() follows.
class Sequence {
 public:
  Sequence(const std::filesystem::path& root, int id, const InputMapping& input = {});

  int id() const { return id_; }
  const std::filesystem::path& dir() const { return dir_; }
  size_t size() const { return frames_.size(); }
  // Frame number of the i-th scan (NNNNNN of its file name).
  int frame(size_t i) const { return frames_.at(i); }
  // The i-th scan's point file.
  const std::filesystem::path& scan_path(size_t i) const;
  std::filesystem::path label_path(size_t i) const;
  bool has_labels(size_t i) const;
  bool has_poses() const { return !poses_.empty(); }
  const InputMapping& input() const { return input_; }
  // LiDAR-frame pose of scan i; requires poses.txt and calib.txt (Error otherwise).
  const Pose& pose(size_t i) const;
  // Transform of scan j's points into scan i's LiDAR frame: inv(T_i) * T_j.
  Pose relative(size_t i, size_t j) const;
  // Scan i with its labels when present, mapped by input().
  Scan load(size_t i) const;

 private:
  std::filesystem::path dir_;
  int id_;
  InputMapping input_;
  std::vector<int> frames_;
  std::vector<std::filesystem::path> scan_paths_;  // one a frame
  std::vector<Pose> poses_;  // LiDAR frame, empty without poses.txt
};

// Sequence ids present under ROOT/sequences, sorted.
std::vector<int> list_sequences(const std::filesystem::path& root);
// SemanticKITTI splits: train 00-07, 09, 10; validation 08.
std::vector<int> split_sequences(const std::string& split);
// "08" for 8.
std::string sequence_name(int id);

}  // namespace pillarseg
