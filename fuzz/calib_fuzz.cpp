// Fuzz target: a SemanticKITTI calib.txt, read_calib, and the LiDAR-frame pose of an identity
// cam0 pose (engine/data/semantickitti.hpp): a Tr read is finite and invertible.
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
  const std::filesystem::path path = fuzz::write_scratch("calib.txt", data, size);
  try {
    const pillarseg::Calib calib = pillarseg::read_calib(path);
    fuzz::check(calib.Tr.allFinite() && calib.Tr.row(3) == Eigen::RowVector4d(0, 0, 0, 1),
                "Tr is finite with the bottom row 0 0 0 1");
    fuzz::check(calib.Tr.topLeftCorner<3, 3>().determinant() != 0, "Tr is invertible");
    const std::vector<pillarseg::Pose> identity(1, pillarseg::Pose::Identity());
    static_cast<void>(pillarseg::lidar_poses(identity, calib));
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
