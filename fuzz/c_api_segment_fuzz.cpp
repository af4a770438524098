// Fuzz target: pillarseg_segment (include/pillarseg/pillarseg.h) on segmenters of the tiny model
// (fuzz/tiny_model.yaml) opened once. Input: a flags byte, then the points as float32 x y z r
// records (NaN, Inf and huge coordinates included; a trailing partial record is ignored; none is
// a scan of 0 points). Flags: 1 probabilities, 2 the segmenter masking unobserved cells, 4 points
// NULL with the count from the next 8 bytes, 8 labels NULL. A call with valid arguments succeeds
// with class ids 0..12 and probabilities in [0, 1]; any other fails with a clean error.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <vector>

#include "fuzz/fuzz_support.hpp"
#include "pillarseg/pillarseg.h"

namespace fuzz = pillarseg::fuzz;

namespace {

pillarseg_segmenter* open_tiny(int mask_unobserved) {
  pillarseg_options options;
  pillarseg_default_options(&options);
  options.threads = 1;
  options.mask_unobserved = mask_unobserved;
  char error[512];
  pillarseg_segmenter* s =
      pillarseg_open(fuzz::tiny_checkpoint().c_str(), nullptr, &options, error, sizeof error);
  if (s == nullptr) {
    std::fprintf(stderr, "fuzz harness: cannot open the tiny model: %s\n", error);
    std::abort();
  }
  return s;
}

pillarseg_segmenter* segmenter(bool masked) {
  static pillarseg_segmenter* const plain = open_tiny(0);
  static pillarseg_segmenter* const masking = open_tiny(1);
  return masked ? masking : plain;
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  segmenter(false);
  segmenter(true);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  fuzz::InputCursor in(data, size);
  const auto flags = in.take<uint8_t>();
  const bool want_probabilities = (flags & 1) != 0, null_points = (flags & 4) != 0,
             null_labels = (flags & 8) != 0;
  pillarseg_segmenter* s = segmenter((flags & 2) != 0);
  int width = 0, height = 0;
  pillarseg_grid(s, &width, &height);
  const size_t cells = static_cast<size_t>(width) * static_cast<size_t>(height);

  size_t num_points = 0;
  std::vector<float> xyzr;
  if (null_points) {
    num_points = in.take<uint64_t>();
  } else {
    num_points = in.remaining() / 16;
    xyzr.resize(4 * num_points);
    if (num_points > 0) std::memcpy(xyzr.data(), in.rest(), 16 * num_points);
  }
  std::vector<uint8_t> labels(cells, 0xFF);
  std::vector<float> probabilities(want_probabilities ? 12 * cells : 0, -1.0f);
  char error[512];
  const int rc = pillarseg_segment(
      s, null_points ? nullptr : xyzr.data(), num_points, null_labels ? nullptr : labels.data(),
      want_probabilities ? probabilities.data() : nullptr, error, sizeof error);
  const bool valid = !null_labels && !(null_points && num_points > 0);
  if (rc != 0) {
    fuzz::check_c_api_error("pillarseg_segment", error);
    fuzz::check(!valid, "pillarseg_segment succeeds on valid arguments");
    return 0;
  }
  fuzz::check(valid, "pillarseg_segment fails on invalid arguments");
  for (const uint8_t label : labels) fuzz::check(label <= PILLARSEG_NUM_CLASSES, "class ids 0..12");
  for (const float p : probabilities)
    fuzz::check(std::isfinite(p) && p >= 0 && p <= 1, "probabilities in [0, 1]");
  return 0;
}
