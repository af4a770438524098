// Fuzz target: a ground-truth cache entry (engine/data/cache.hpp), read through Cache::load of
// every element type the ground truth stores (u8 maps, u32 observability, f32 occupancy, i64
// neighbour lists) and Cache::load_bytes, whose blob decode_labelled_points reads
// (engine/data/ground_truth.hpp). The input is the whole file, at the path of one fixed key; an
// entry whose header holds another key is a miss. A hit has the payload its shape says.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include "core/error.hpp"
#include "engine/data/cache.hpp"
#include "engine/data/ground_truth.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

namespace {

// make_seeds.py writes its seeds under this key.
const pillarseg::CacheKey kKey{"/fuzz/sequences/00", 0, "gt-sparse", 0x0123456789abcdefu,
                               0xfedcba9876543210u};

template <class T>
void load(const pillarseg::Cache& cache, size_t file_size) {
  if (const std::optional<pillarseg::Tensor<T>> tensor = cache.load<T>(kKey))
    fuzz::check(static_cast<size_t>(tensor->numel()) * sizeof(T) < file_size,
                "a hit's payload lies inside the file");
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const pillarseg::Cache cache(fuzz::scratch_dir() / "cache");
  static const std::filesystem::path path = [] {
    std::filesystem::path file = cache.path_of(kKey);
    std::filesystem::create_directories(file.parent_path());
    return file;
  }();
  fuzz::write_file(path, data, size);
  try {
    load<uint8_t>(cache, size);
    load<uint32_t>(cache, size);
    load<float>(cache, size);
    load<int64_t>(cache, size);
    if (const std::optional<std::vector<char>> blob = cache.load_bytes(kKey)) {
      fuzz::check(blob->size() < size, "a hit's blob lies inside the file");
      if (const std::optional<pillarseg::LabelledPoints> set =
              pillarseg::decode_labelled_points(*blob))
        fuzz::check(set->points.size() == set->classes.size(), "one class id per point");
    }
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
