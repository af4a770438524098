// Fuzz target: a SemanticKITTI .label file, read_labels, and read_scan of a 4-point .bin file (one
// point NaN) with it (engine/data/semantickitti.hpp): the label count must match the point count.
#include <cstddef>
#include <cstdint>
#include <limits>
#include <vector>

#include "core/error.hpp"
#include "engine/data/semantickitti.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

namespace {

// Three finite points, and a NaN one that read_scan drops with its label.
const std::filesystem::path& four_point_bin() {
  static const std::filesystem::path path = [] {
    const std::vector<pillarseg::Point> points = {
        {1, 2, -1, 0.5f},
        {-3, 0.25f, 0, 0},
        {std::numeric_limits<float>::quiet_NaN(), 0, 0, 0},
        {10, -5, 0.5f, 1}};
    std::filesystem::path file = fuzz::scratch_dir() / "four.bin";
    fuzz::write_file(file, reinterpret_cast<const uint8_t*>(points.data()),
                     points.size() * sizeof(pillarseg::Point));
    return file;
  }();
  return path;
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path path = fuzz::write_scratch("scan.label", data, size);
  try {
    const std::vector<uint32_t> labels = pillarseg::read_labels(path);
    fuzz::check(labels.size() == size / 4, "one label per 4 bytes");
  } catch (const pillarseg::Error&) {
  }
  try {
    const pillarseg::Scan scan = pillarseg::read_scan(four_point_bin(), path);
    fuzz::check(scan.points.size() == 3 && scan.labels.size() == 3 && scan.dropped_nonfinite == 1,
                "3 points kept with their labels, 1 dropped");
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
