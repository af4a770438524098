// Fuzz target: pillarseg_open (include/pillarseg/pillarseg.h) of the tiny model's checkpoint with
// fuzzed options and run-config text (fuzz/tiny_model.yaml is the seed), then pillarseg_segment
// of a fixed scan on what opened. Input:
//   u8 choices: bits 0-1 device (cpu, emu, cuda, a string), bits 2-3 convolution (own, cudnn,
//               cublas, a string), bits 4-5 precision (fp32, bf16, fp16, a string), bit 6 options
//               NULL, bit 7 a config path
//   u8 struct_size (0: sizeof(pillarseg_options)), i8 threads, i8 cuda_device, u8 mask_and_flips
//   (bit 0 mask_unobserved, bits 1-2 flips 1, 2, 4 or the whole byte as a signed value),
//   the chosen strings (a length byte each), then the config text.
// A config whose grid has more than 2^16 cells or 64 layers is valid but too slow to fuzz and is
// skipped. A failure must be a clean error; what opens must segment.
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "engine/model/run_config.hpp"
#include "fuzz/fuzz_support.hpp"
#include "pillarseg/pillarseg.h"

namespace fuzz = pillarseg::fuzz;

namespace {

// One of three names by the 2-bit choice, or (choice 3) a string from the input.
const char* choose(unsigned choice, const char* const (&names)[3], const std::string& text) {
  return choice < 3 ? names[choice] : text.c_str();
}

// 96 points in and around the tiny grid, and a NaN one.
std::vector<float> fixed_scan() {
  std::vector<float> xyzr;
  for (int i = 0; i < 96; ++i)
    xyzr.insert(
        xyzr.end(),
        {-7.0f + 0.146f * static_cast<float>(i), -3.5f + 0.073f * static_cast<float>((i * 7) % 96),
         -1.5f + 0.02f * static_cast<float>(i % 50), 0.01f * static_cast<float>(i % 100)});
  xyzr.insert(xyzr.end(), {std::numeric_limits<float>::quiet_NaN(), 0.0f, 0.0f, 0.0f});
  return xyzr;
}

bool too_slow_to_fuzz(const std::string& config_text) {
  try {
    const pillarseg::GridSpec grid =
        pillarseg::parse_run_config(config_text, "fuzz input").model.grid;
    return grid.cells() > (int64_t{1} << 16) || grid.layers() > 64;
  } catch (const pillarseg::Error&) {
    return false;  // pillarseg_open must fail on it cleanly
  }
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  fuzz::tiny_checkpoint();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const char* const kDevices[3] = {"cpu", "emu", "cuda"};
  static const char* const kConvolutions[3] = {"own", "cudnn", "cublas"};
  static const char* const kPrecisions[3] = {"fp32", "bf16", "fp16"};
  fuzz::InputCursor in(data, size);
  const auto choices = in.take<uint8_t>();
  const auto struct_size = in.take<uint8_t>();
  pillarseg_options options;
  pillarseg_default_options(&options);
  if (struct_size != 0) options.struct_size = struct_size;
  options.threads = in.take<int8_t>();
  options.cuda_device = in.take<int8_t>();
  const auto mask_and_flips = in.take<uint8_t>();
  options.mask_unobserved = mask_and_flips & 1u;
  static const int kFlips[3] = {1, 2, 4};
  const unsigned flips_choice = (mask_and_flips >> 1) & 3u;
  options.flips = flips_choice < 3 ? kFlips[flips_choice] : static_cast<int8_t>(mask_and_flips);
  const std::string device = (choices & 3u) == 3 ? in.take_string() : "";
  const std::string convolution = ((choices >> 2) & 3u) == 3 ? in.take_string() : "";
  const std::string precision = ((choices >> 4) & 3u) == 3 ? in.take_string() : "";
  options.device = choose(choices & 3u, kDevices, device);
  options.convolution = choose((choices >> 2) & 3u, kConvolutions, convolution);
  options.precision = choose((choices >> 4) & 3u, kPrecisions, precision);
  const bool null_options = (choices & 64) != 0, with_config = (choices & 128) != 0;

  std::optional<std::filesystem::path> config_path;
  if (with_config) {
    const std::string text(reinterpret_cast<const char*>(in.rest()), in.remaining());
    if (too_slow_to_fuzz(text)) return 0;
    config_path = fuzz::scratch_dir() / "config.yaml";
    fuzz::write_file(*config_path, text);
  }
  char error[512];
  pillarseg_segmenter* s =
      pillarseg_open(fuzz::tiny_checkpoint().c_str(), config_path ? config_path->c_str() : nullptr,
                     null_options ? nullptr : &options, error, sizeof error);
  if (s == nullptr) {
    fuzz::check_c_api_error("pillarseg_open", error);
    return 0;
  }
  int width = 0, height = 0;
  pillarseg_grid(s, &width, &height);
  std::vector<uint8_t> labels(static_cast<size_t>(width) * static_cast<size_t>(height));
  static const std::vector<float> scan = fixed_scan();
  const int rc = pillarseg_segment(s, scan.data(), scan.size() / 4, labels.data(), nullptr, error,
                                   sizeof error);
  pillarseg_close(s);
  if (rc != 0) fuzz::check_c_api_error("pillarseg_segment", error);
  fuzz::check(rc == 0, "a segmenter that opened segments a scan");
  return 0;
}
