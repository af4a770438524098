// Fuzz target: a SemanticKITTI .bin point cloud, read_scan (engine/data/semantickitti.hpp).
// Every whole 16-byte record is a point kept or counted as dropped; kept points are finite.
#include <cmath>
#include <cstddef>
#include <cstdint>

#include "core/error.hpp"
#include "engine/data/semantickitti.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path path = fuzz::write_scratch("scan.bin", data, size);
  try {
    const pillarseg::Scan scan = pillarseg::read_scan(path);
    fuzz::check(scan.points.size() + scan.dropped_nonfinite == size / 16,
                "kept + dropped points == records");
    fuzz::check(scan.labels.empty(), "no labels without a .label file");
    for (const pillarseg::Point& p : scan.points)
      fuzz::check(
          std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z) && std::isfinite(p.r),
          "kept points are finite");
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
