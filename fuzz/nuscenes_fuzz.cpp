// Fuzz target: a nuScenes .pcd.bin file (x y z intensity ring float32 records), read_points
// (engine/data/point_formats.hpp). Every whole 20-byte record is a point kept or counted as
// dropped; kept points are finite.
#include <cstddef>
#include <cstdint>

#include "core/error.hpp"
#include "engine/data/point_formats.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path path = fuzz::write_scratch("scan.pcd.bin", data, size);
  try {
    const pillarseg::Scan scan = pillarseg::read_points(path, pillarseg::PointFormat::Nuscenes);
    fuzz::check(scan.points.size() + scan.dropped_nonfinite == size / 20, "kept + dropped points == records");
    fuzz::check_scan(scan);
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
