#include "engine/sim/simulate.hpp"

#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include <cmath>
#include <numbers>

#include "core/eigen.hpp"
#include "core/error.hpp"
#include "core/rng.hpp"

namespace pillarseg::sim {

namespace fs = std::filesystem;

namespace {

constexpr double kPi = std::numbers::pi;
constexpr double kMovingReach =
    20.0;  // moving agents this far beyond the LiDAR's range are posed too

// KITTI's camera projections (sequences 00-02); the engine does not use them, but the files
// must hold them.
Calib kitti_like_calib(uint64_t seed) {
  Calib calib;
  const double f = 718.856, cx = 607.1928, cy = 185.2157;
  const double tx[4] = {0.0, -386.1448, 45.38225, -337.2877};
  const double ty[4] = {0.0, 0.0, -0.1130887, 2.369057};
  const double tz[4] = {0.0, 0.0, 3.779761e-3, 4.915215e-3};
  for (int i = 0; i < 4; ++i) {
    Eigen::Matrix<double, 3, 4> p;
    p << f, 0, cx, tx[i], 0, f, cy, ty[i], 0, 0, 1, tz[i];
    calib.P[static_cast<size_t>(i)] = p;
  }
  // Tr: KITTI's axis swap (LiDAR x forward -> cam0 z, y left -> -x, z up -> -y) and lever arm,
  // with a small rotation and offset of the mounting, different for every sequence.
  Rng rng = Rng::derive(seed, 0xCA11B);
  Eigen::Matrix3d swap;
  swap << 0, -1, 0, 0, 0, -1, 1, 0, 0;
  // One draw per statement: the order of draws must not depend on the compiler.
  const double deg = kPi / 180.0;
  const double roll = rng.normal(0.0, 0.3 * deg);
  const double pitch = rng.normal(0.0, 0.3 * deg);
  const double yaw = rng.normal(0.0, 0.3 * deg);
  const double dx = rng.normal(0.0, 0.01);
  const double dy = rng.normal(0.0, 0.01);
  const double dz = rng.normal(0.0, 0.01);
  const Eigen::Matrix3d tilt = (Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()) *
                                Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
                                Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()))
                                   .toRotationMatrix();
  calib.Tr = Pose::Identity();
  calib.Tr.topLeftCorner<3, 3>() = tilt * swap;
  calib.Tr.topRightCorner<3, 1>() = Eigen::Vector3d(dx, -0.08 + dy, -0.27 + dz);
  return calib;
}

}  // namespace

uint64_t sequence_seed(uint64_t seed, int id) {
  return Rng::derive(seed, 0x5E9, static_cast<uint64_t>(id)).next_u64();
}

SequenceSimulator::SequenceSimulator(uint64_t seed, int scans, int64_t points_per_scan)
    : seed_(seed),
      scans_(scans),
      city_(City::generate(seed, scans)),
      lidar_(LidarModel::hdl64e(LidarModel::azimuth_steps_for(points_per_scan))),
      calib_(kitti_like_calib(seed)) {
  lidar_.vary(seed);
}

Pose SequenceSimulator::lidar_pose_world(int i) const {
  PS_CHECK(i >= 0 && i < scans_, "scan {} out of range: the sequence has {} scans", i, scans_);
  return city_.lidar_pose(scan_time(i));
}

std::vector<Pose> SequenceSimulator::cam0_poses() const {
  // pose_i = Tr inv(L_0) L_i inv(Tr), so that inv(Tr) pose_i Tr = inv(L_0) L_i.
  const Pose first_inv = lidar_pose_world(0).inverse();
  const Pose tr_inv = calib_.Tr.inverse();
  std::vector<Pose> poses;
  poses.reserve(static_cast<size_t>(scans_));
  for (int i = 0; i < scans_; ++i)
    poses.push_back(calib_.Tr * first_inv * lidar_pose_world(i) * tr_inv);
  return poses;
}

SimScan SequenceSimulator::scan(int i) const {
  const Pose pose = lidar_pose_world(i);
  std::vector<Primitive> moving;
  city_.moving_primitives(scan_time(i), pose.topRightCorner<2, 1>(),
                          lidar_.max_range + kMovingReach, moving);
  const SceneGrid moving_scene(std::move(moving), 2.0);
  return cast_scan(lidar_, city_, moving_scene, pose,
                   Rng::derive(seed_, 0x5CA4, static_cast<uint64_t>(i)).next_u64());
}

void SequenceSimulator::write(const fs::path& dir, Progress* progress, int64_t done_before) const {
  fs::create_directories(dir / "velodyne");
  fs::create_directories(dir / "labels");
  write_calib(dir / "calib.txt", calib_);
  write_poses(dir / "poses.txt", cam0_poses());
  for (int i = 0; i < scans_; ++i) {
    const SimScan s = scan(i);
    write_bin(dir / "velodyne" / fmt::format("{:06}.bin", i), s.points);
    write_labels(dir / "labels" / fmt::format("{:06}.label", i), s.labels);
    if (progress) progress->update(done_before + i + 1);
  }
}

void simulate(const SimulateOptions& options) {
  PS_CHECK(!options.out.empty(), "simulate: --out must name the output directory");
  PS_CHECK(options.sequences >= 1, "simulate: --sequences must be >= 1, got {}", options.sequences);
  PS_CHECK(options.scans >= 1, "simulate: --scans must be >= 1, got {}", options.scans);
  PS_CHECK(options.first_sequence >= 0 && options.first_sequence + options.sequences <= 100,
           "simulate: sequence ids {}..{} do not fit in two digits (00-99)", options.first_sequence,
           options.first_sequence + options.sequences - 1);
  Progress progress("simulate", static_cast<int64_t>(options.sequences) * options.scans, "scans");
  for (int q = 0; q < options.sequences; ++q) {
    const int id = options.first_sequence + q;
    const SequenceSimulator sim(sequence_seed(options.seed, id), options.scans,
                                options.points_per_scan);
    const fs::path dir = options.out / "sequences" / sequence_name(id);
    sim.write(dir, &progress, static_cast<int64_t>(q) * options.scans);
    spdlog::info("sequence {}: {} scans, {} streets, {} moving agents -> {}", sequence_name(id),
                 options.scans, sim.city().streets().size(), sim.city().movers().size(),
                 dir.string());
  }
  progress.finish();
}

}  // namespace pillarseg::sim
