// Fuzz target: JSON text, json::parse (weights_io/json.hpp), the reader of safetensors headers.
// A document that parses must dump to text that parses back and dumps to the same text.
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "core/error.hpp"
#include "fuzz/fuzz_support.hpp"
#include "weights_io/json.hpp"

namespace fuzz = pillarseg::fuzz;
namespace json = pillarseg::json;

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  std::optional<json::Value> value;
  try {
    value = json::parse(text, "fuzz input");
  } catch (const pillarseg::Error&) {
    return 0;
  }
  // From here on the document is valid: an Error escaping is a finding.
  const std::string dumped = json::dump(*value);
  fuzz::check(json::is_valid_utf8(dumped), "dump writes UTF-8");
  fuzz::check(json::dump(json::parse(dumped, "dumped fuzz input")) == dumped,
              "dump is a fixed point of parse");
  return 0;
}
