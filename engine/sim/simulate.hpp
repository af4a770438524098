// Simulated SemanticKITTI sequences: per sequence a procedural city (city.hpp), the ego's drive
// along its main street at 10 Hz, and one LiDAR revolution per scan (lidar.hpp), written as
// ROOT/sequences/SS/{velodyne/NNNNNN.bin, labels/NNNNNN.label, poses.txt, calib.txt}.
// poses.txt holds cam0 poses relative to the first cam0 frame and calib.txt a KITTI-like
// Tr (LiDAR -> cam0), so that lidar_poses() gives the LiDAR's true motion: T_i = inv(L_0) L_i
// for the LiDAR-to-world poses L_i. Same arguments, same files, byte for byte, whatever the
// thread count.
#pragma once

#include <cstdint>
#include <filesystem>
#include <vector>

#include "engine/data/semantickitti.hpp"
#include "engine/sim/city.hpp"
#include "engine/sim/lidar.hpp"
#include "engine/util/progress.hpp"

namespace pillarseg::sim {

struct SimulateOptions {
  std::filesystem::path out;         // ROOT: sequences/SS is written under it
  int sequences = 1;                 // how many sequences
  int scans = 100;                   // scans per sequence
  uint64_t seed = 0;                 // seed of the whole data set
  int first_sequence = 0;            // id of the first sequence; ids first .. first + sequences - 1
  int64_t points_per_scan = 120000;  // target returns per scan (about; the street decides)
};

// Seed of sequence `id` of a data set with seed `seed`.
uint64_t sequence_seed(uint64_t seed, int id);

// One simulated sequence: its city, ego poses, calibration, and scans on demand.
class SequenceSimulator {
 public:
  SequenceSimulator(uint64_t seed, int scans, int64_t points_per_scan = 120000);

  int scans() const { return scans_; }
  static double scan_time(int i) { return i * kScanPeriod; }
  const City& city() const { return city_; }
  const LidarModel& lidar() const { return lidar_; }
  const Calib& calib() const { return calib_; }
  // LiDAR-to-world transform of scan i.
  Pose lidar_pose_world(int i) const;
  // poses.txt: cam0 pose of each scan in the first scan's cam0 frame.
  std::vector<Pose> cam0_poses() const;
  // Scan i: returns in the LiDAR frame with their raw labels.
  SimScan scan(int i) const;
  // Writes the sequence into dir (velodyne/, labels/, poses.txt, calib.txt); after each scan
  // sets progress (when given) to done_before + scans written.
  void write(const std::filesystem::path& dir, Progress* progress = nullptr,
             int64_t done_before = 0) const;

 private:
  uint64_t seed_;
  int scans_;
  City city_;
  LidarModel lidar_;
  Calib calib_;
};

// Writes options.sequences sequences under options.out with a progress display.
void simulate(const SimulateOptions& options);

}  // namespace pillarseg::sim
