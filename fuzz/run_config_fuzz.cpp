// Fuzz target: the run-config YAML, parse_run_config (engine/model/run_config.hpp), the text of
// --config and of every checkpoint's metadata. A config that parses has a valid model whose cell
// counts span its ranges (width x cell = x range, likewise y and z).
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/error.hpp"
#include "engine/model/run_config.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

namespace {

bool spans(int count, double step, double min, double max) {
  return count >= 1 && std::abs(count * step - (max - min)) <= 1e-6 * (max - min);
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  try {
    const pillarseg::RunConfig config = pillarseg::parse_run_config(
        std::string(reinterpret_cast<const char*>(data), size), "fuzz input");
    const pillarseg::GridSpec& g = config.model.grid;
    fuzz::check(spans(g.width(), g.cell, g.x_min, g.x_max) &&
                    spans(g.height(), g.cell, g.y_min, g.y_max) &&
                    spans(g.layers(), g.voxel_z, g.z_min, g.z_max),
                "the grid's cell counts span its ranges");
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
