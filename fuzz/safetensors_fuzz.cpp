// Fuzz target: a safetensors file image, SafeTensors::parse (weights_io/safetensors.hpp): the
// length, the JSON header (weights_io/json.hpp) and the payload. A file that parses must convert
// every tensor (get_f32 or get_i64) and serialise to a file that parses back to the same bytes.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "core/error.hpp"
#include "fuzz/fuzz_support.hpp"
#include "weights_io/safetensors.hpp"

namespace fuzz = pillarseg::fuzz;
namespace weights = pillarseg::weights;

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  std::optional<weights::SafeTensors> file;
  try {
    file = weights::SafeTensors::parse(std::span<const uint8_t>(data, size), "fuzz input");
  } catch (const pillarseg::Error&) {
    return 0;
  }
  // From here on the file is valid: an Error escaping is a finding.
  for (const std::string& name : file->names()) {
    const weights::TensorRecord& record = file->at(name);
    int64_t numel = 1;
    for (int64_t d : record.shape) numel *= d;
    fuzz::check(
        static_cast<int64_t>(record.bytes.size()) == numel * weights::dtype_size(record.dtype),
        "a tensor's bytes match its shape and dtype");
    if (weights::is_floating(record.dtype))
      fuzz::check(file->get_f32(name).numel() == numel, "get_f32 keeps the element count");
    else
      fuzz::check(static_cast<int64_t>(file->get_i64(name).size()) == numel,
                  "get_i64 keeps the element count");
  }
  const std::vector<uint8_t> bytes = file->serialize();
  const weights::SafeTensors again = weights::SafeTensors::parse(bytes, "serialized fuzz input");
  fuzz::check(again.names() == file->names() && again.metadata == file->metadata,
              "serialize and parse keep the names and the metadata");
  fuzz::check(again.serialize() == bytes, "serialize is a fixed point of parse");
  return 0;
}
