// File helpers: whole-file reads with clear errors, and atomic writes (write to a temporary
// file beside the target, then rename), so that a failed or interrupted write never leaves a
// half-written file under the target name.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <iosfwd>
#include <string>
#include <vector>

namespace pillarseg {

std::vector<char> read_file_bytes(const std::filesystem::path& path);
std::string read_file_text(const std::filesystem::path& path);

// Calls write(out) on a stream to "path.tmp-<pid>-<n>", flushes, checks, and renames onto path.
// Creates missing parent directories.
void write_file_atomic(const std::filesystem::path& path, const std::function<void(std::ostream&)>& write);
void write_file_atomic(const std::filesystem::path& path, const void* data, size_t size);

// Lower-cased extension with the dot (".png"); empty if none.
std::string lower_extension(const std::filesystem::path& path);

}  // namespace pillarseg
