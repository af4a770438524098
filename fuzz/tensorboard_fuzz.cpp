// Fuzz target: a TensorBoard event file (engine/util/tensorboard.hpp) as `pillarseg plot`'s
// reader and `train --resume` read it: read_event_scalars (records, CRC-32C, the Event and
// Summary protocol buffers), then EventWriter's resume cut to a step from the input's first
// bytes, whose file must read back whole (not truncated) with no step beyond the cut.
#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/error.hpp"
#include "engine/util/tensorboard.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::filesystem::path run_dir = [] {
    std::filesystem::path dir = fuzz::scratch_dir() / "run";
    std::filesystem::create_directories(dir);
    return dir;
  }();
  const std::filesystem::path path = pillarseg::EventWriter::path_in(run_dir);
  fuzz::write_file(path, data, size);
  size_t scalars = 0;
  try {
    bool truncated = false;
    scalars = pillarseg::read_event_scalars(path, &truncated).size();
  } catch (const pillarseg::Error&) {
    return 0;  // a record whose CRCs hold but whose event does not parse: plot stops there
  }
  fuzz::InputCursor in(data, size);
  const int64_t keep_through = in.take<int8_t>();
  { pillarseg::EventWriter resumed(run_dir, /*resume=*/true, keep_through); }
  bool truncated = true;
  const std::vector<pillarseg::EventScalar> kept = pillarseg::read_event_scalars(path, &truncated);
  fuzz::check(!truncated, "the resumed file has no cut-short record");
  fuzz::check(kept.size() <= scalars, "resume keeps a subset of the scalars");
  for (const pillarseg::EventScalar& s : kept) fuzz::check(s.step <= keep_through, "no step beyond the cut");
  return 0;
}
