// Fuzz target: a PLY file (ascii, binary little or big endian), read_points
// (engine/data/point_formats.hpp). Kept points are finite; a file without labels gives none.
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
  const std::filesystem::path path = fuzz::write_scratch("scan.ply", data, size);
  try {
    fuzz::check_scan(pillarseg::read_points(path, pillarseg::PointFormat::Ply));
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
