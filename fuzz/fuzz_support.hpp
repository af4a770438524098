// What the fuzz targets (fuzz/*_fuzz.cpp) share: a per-process scratch directory for readers that
// take a path, a cursor that splits one input into fields, the tiny model the C API and
// checkpoint targets load, and the check that a C API error message is a clean one.
//
// A target's contract: a reader's pillarseg::Error (the C API: its error return) is the expected
// outcome for bad input and is swallowed; anything else (another exception type, std::bad_alloc
// included, a crash, a sanitizer report) escapes or aborts, and is a finding.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <string>
#include <string_view>
#include <type_traits>

#include "core/point.hpp"

namespace pillarseg::fuzz {

// Silences the engine's log (a warning per corrupt input would dominate the run time).
void quiet_logs();

// $TMPDIR/pillarseg-fuzz-<pid> (or /tmp/...), created on first use and removed at exit.
const std::filesystem::path& scratch_dir();

// Writes data[0 .. size) to `path` (created or truncated; not atomic: one process, one writer).
void write_file(const std::filesystem::path& path, const uint8_t* data, size_t size);
void write_file(const std::filesystem::path& path, std::string_view text);

// scratch_dir() / name holding data[0 .. size).
std::filesystem::path write_scratch(std::string_view name, const uint8_t* data, size_t size);

// fuzz/tiny_model.yaml: the grid, model and a short training run of the tiny model (a 32 x 16
// grid); fuzz/make_seeds.py trains the committed checkpoint seeds on the same file.
const std::string& tiny_model_config();
// A checkpoint of the tiny model with seeded random weights, written once into scratch_dir().
const std::filesystem::path& tiny_checkpoint();

// Aborts, printing `what`, when an invariant of a reader's result does not hold.
void check(bool condition, std::string_view what);
// The invariants of a scan read from a point file without labels: every kept point finite, no labels.
void check_scan(const Scan& scan);

// Aborts, printing the message, when a C API error is not a clean pillarseg::Error (the API turns
// any other exception into "unexpected error" and std::bad_alloc into "out of memory").
void check_c_api_error(const char* function, const char* error);

// Splits an input into fields, front to back; past the end, fields read as zero or empty.
class InputCursor {
 public:
  InputCursor(const uint8_t* data, size_t size) : data_(data), size_(size) {}

  template <class T>
  requires std::is_trivially_copyable_v<T> T take() {
    T value{};
    const size_t n = std::min(sizeof value, remaining());
    if (n > 0) std::memcpy(&value, data_ + pos_, n);
    pos_ += n;
    return value;
  }
  // A string of up to max_size bytes, its length given by the next byte.
  std::string take_string(size_t max_size = 255) {
    const size_t n = std::min({static_cast<size_t>(take<uint8_t>()), max_size, remaining()});
    std::string text(reinterpret_cast<const char*>(data_ + pos_), n);
    pos_ += n;
    return text;
  }
  const uint8_t* rest() const { return data_ + pos_; }
  size_t remaining() const { return size_ - pos_; }

 private:
  const uint8_t* data_;
  size_t size_;
  size_t pos_ = 0;
};

}  // namespace pillarseg::fuzz
