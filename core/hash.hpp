// Hasher: FNV-1a 64 over values and bytes; stable across runs and machines (little-endian).
// Used for cache keys of ground truth and occupancy maps.
#pragma once

#include <cstdint>
#include <cstring>
#include <string>
#include <string_view>
#include <type_traits>

namespace pillarseg {

class Hasher {
 public:
  void add_bytes(const void* data, size_t n) {
    const auto* p = static_cast<const unsigned char*>(data);
    for (size_t i = 0; i < n; ++i) {
      h_ ^= p[i];
      h_ *= 0x100000001b3ull;
    }
  }
  template <class T>
    requires std::is_arithmetic_v<T>
  void add(T v) { add_bytes(&v, sizeof v); }
  void add(std::string_view s) {
    add(static_cast<uint64_t>(s.size()));
    add_bytes(s.data(), s.size());
  }
  void add(const std::string& s) { add(std::string_view(s)); }
  uint64_t digest() const { return h_; }

 private:
  uint64_t h_ = 0xcbf29ce484222325ull;
};

}  // namespace pillarseg
