// Fuzz target: a training run's metrics.jsonl as `pillarseg plot` reads it (read_training_log,
// engine/util/metrics_log.hpp) and as `train --resume` cuts it (kept_metrics_lines,
// engine/train/trainer.hpp). What resume keeps is whole input lines, in order, none beyond the
// checkpoint's epoch and step, and cutting again keeps all of it.
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "core/error.hpp"
#include "engine/train/trainer.hpp"
#include "engine/util/metrics_log.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path path = fuzz::write_scratch("metrics.jsonl", data, size);
  try {
    const pillarseg::TrainingLog log = pillarseg::read_training_log(path);
    for (const pillarseg::EvalRecord& e : log.evals)
      fuzz::check(e.confusion.empty() || e.confusion.size() == pillarseg::kNumClasses,
                  "a confusion matrix has 12 rows");
  } catch (const pillarseg::Error&) {
  }
  // The checkpoint to resume from: epoch and step from the input's first bytes.
  fuzz::InputCursor in(data, size);
  const int64_t epoch = in.take<uint8_t>(), step = in.take<uint16_t>();
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  const std::string kept = pillarseg::kept_metrics_lines(text, epoch, step);
  fuzz::check(kept.empty() || kept.back() == '\n', "kept lines end in a newline");
  size_t from = 0;  // every kept line is a later line of the input
  for (size_t begin = 0; begin < kept.size();) {
    const size_t end = kept.find('\n', begin);
    const std::string_view line = std::string_view(kept).substr(begin, end + 1 - begin);
    size_t at = text.find(line, from);
    while (at != std::string_view::npos && at != 0 && text[at - 1] != '\n')
      at = text.find(line, at + 1);
    fuzz::check(at != std::string_view::npos, "a kept line is a whole line of the log");
    from = at + line.size();
    begin = end + 1;
  }
  fuzz::check(pillarseg::kept_metrics_lines(kept, epoch, step) == kept, "cutting twice is cutting once");
  return 0;
}
