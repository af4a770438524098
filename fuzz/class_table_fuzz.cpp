// Fuzz target: the class-table override YAML, load_class_table (engine/data/class_table_yaml.hpp):
// every raw id maps to a class id 0..12.
#include <cstddef>
#include <cstdint>

#include "core/classes.hpp"
#include "core/error.hpp"
#include "engine/data/class_table_yaml.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path path = fuzz::write_scratch("classes.yaml", data, size);
  try {
    const pillarseg::ClassTable table = pillarseg::load_class_table(path.string());
    for (uint32_t raw = 0; raw <= 0xFFFFu; ++raw)
      fuzz::check(table.class_of(raw) < pillarseg::kNumClassIds, "a raw id maps to a class id");
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
