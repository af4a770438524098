// Errors: every failure a user can cause is a pillarseg::Error whose message says what was
// expected and what was given (and names the file or argument involved).
#pragma once

#include <fmt/core.h>

#include <stdexcept>
#include <string>

namespace pillarseg {

class Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

}  // namespace pillarseg

// PS_CHECK(cond, "format {}", args...): throws pillarseg::Error with the formatted message.
#define PS_CHECK(cond, ...)                                        \
  do {                                                             \
    if (!(cond)) throw ::pillarseg::Error(fmt::format(__VA_ARGS__)); \
  } while (0)

#define PS_FAIL(...) throw ::pillarseg::Error(fmt::format(__VA_ARGS__))
