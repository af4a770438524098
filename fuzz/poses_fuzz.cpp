// Fuzz target: a SemanticKITTI poses.txt, read_poses, and the LiDAR-frame poses made from it
// (engine/data/semantickitti.hpp): every pose read is finite with the bottom row 0 0 0 1.
#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/error.hpp"
#include "engine/data/semantickitti.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path path = fuzz::write_scratch("poses.txt", data, size);
  try {
    const std::vector<pillarseg::Pose> poses = pillarseg::read_poses(path);
    for (const pillarseg::Pose& p : poses)
      fuzz::check(p.allFinite() && p.row(3) == Eigen::RowVector4d(0, 0, 0, 1),
                  "a pose is finite with the bottom row 0 0 0 1");
    pillarseg::Calib calib;
    calib.Tr << 0, -1, 0, 0, 0, 0, -1, 0, 1, 0, 0, 0, 0, 0, 0, 1;
    fuzz::check(pillarseg::lidar_poses(poses, calib).size() == poses.size(),
                "one LiDAR pose per pose");
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
