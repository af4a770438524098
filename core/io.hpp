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

// How far a write_file_atomic survives: kProcess, a killed process (the rename is atomic: the
// target is the old file or the whole new one); kPowerLoss also a crash of the machine (the file
// and then its directory are fsync'ed around the rename) - for checkpoints.
enum class Durability { kProcess, kPowerLoss };

// Calls write(out) on a stream to the temporary "path.tmp-<host>-<pid>-<n>" (a file descriptor
// of its own: a failing write's errno is kept), checks every write and the close, and renames it
// onto path. Creates missing parent directories. On any failure the temporary file is removed,
// the target is unchanged, and the Error names the target and the cause ("no space left on
// device" for a full file system or quota).
void write_file_atomic(const std::filesystem::path& path, const std::function<void(std::ostream&)>& write,
                       Durability durability = Durability::kProcess);
void write_file_atomic(const std::filesystem::path& path, const void* data, size_t size,
                       Durability durability = Durability::kProcess);

// What a failed write's errno means for the user: "no space left on device (...)" for a full
// file system or quota (ENOSPC, EDQUOT), else strerror's text.
std::string write_error_cause(int err);

// Removes the temporary files of write_file_atomic that a killed process left in `dir` (and its
// subdirectories with `recursive`): those of this host whose process no longer runs. Another
// host's, and a live process's, are kept (a shared cache directory). Returns how many it removed.
size_t remove_stale_temporaries(const std::filesystem::path& dir, bool recursive);

// Lower-cased extension with the dot (".png"); empty if none.
std::string lower_extension(const std::filesystem::path& path);

}  // namespace pillarseg
