// Force-included into every source of the fuzz build (scripts/fuzz.sh: -include). Debian's clang 14
// lacks __builtin_source_location, so libstdc++ 12's <source_location> (kernels/common.cuh) then
// declares nothing; this declares std::source_location on the __builtin_FILE/LINE/... builtins
// clang 14 has (current() is constexpr: clang 14 rejects a consteval one in a default argument).
// Compilers with the builtin get the standard one.
#pragma once

#include <version>

#if defined(__clang__) && !__has_builtin(__builtin_source_location) && \
    !defined(__cpp_lib_source_location)
#include <cstdint>

namespace std {

struct source_location {
  static constexpr source_location current(const char* file = __builtin_FILE(),
                                           const char* function = __builtin_FUNCTION(),
                                           uint_least32_t line = __builtin_LINE(),
                                           uint_least32_t column = __builtin_COLUMN()) noexcept {
    source_location where;
    where.file_ = file;
    where.function_ = function;
    where.line_ = line;
    where.column_ = column;
    return where;
  }
  constexpr source_location() noexcept = default;
  constexpr uint_least32_t line() const noexcept { return line_; }
  constexpr uint_least32_t column() const noexcept { return column_; }
  constexpr const char* file_name() const noexcept { return file_; }
  constexpr const char* function_name() const noexcept { return function_; }

 private:
  const char* file_ = "";
  const char* function_ = "";
  uint_least32_t line_ = 0;
  uint_least32_t column_ = 0;
};

}  // namespace std
#endif
