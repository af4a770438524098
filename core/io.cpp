#include "core/io.hpp"

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <sstream>

#include <unistd.h>

#include "core/error.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

std::vector<char> read_file_bytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  PS_CHECK(in, "{}: cannot open for reading: {}", path.string(), std::strerror(errno));
  in.seekg(0, std::ios::end);
  const std::streamoff size = in.tellg();
  PS_CHECK(size >= 0, "{}: cannot determine the file size", path.string());
  in.seekg(0, std::ios::beg);
  std::vector<char> bytes(static_cast<size_t>(size));
  if (size > 0) in.read(bytes.data(), size);
  PS_CHECK(in.good() || in.eof(), "{}: read failed", path.string());
  PS_CHECK(in.gcount() == size || size == 0, "{}: read {} of {} bytes", path.string(), in.gcount(), size);
  return bytes;
}

std::string read_file_text(const fs::path& path) {
  const auto bytes = read_file_bytes(path);
  return std::string(bytes.begin(), bytes.end());
}

void write_file_atomic(const fs::path& path, const std::function<void(std::ostream&)>& write) {
  static std::atomic<uint64_t> counter{0};
  if (path.has_parent_path()) {
    std::error_code ec;
    fs::create_directories(path.parent_path(), ec);
    PS_CHECK(!ec, "{}: cannot create directory {}: {}", path.string(), path.parent_path().string(),
             ec.message());
  }
  const fs::path tmp = path.string() + ".tmp-" + std::to_string(::getpid()) + "-" +
                       std::to_string(counter.fetch_add(1));
  try {
    {
      std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
      PS_CHECK(out, "{}: cannot open for writing: {}", tmp.string(), std::strerror(errno));
      write(out);
      out.flush();
      PS_CHECK(out.good(), "{}: write failed (disk full?)", path.string());
    }
    std::error_code ec;
    fs::rename(tmp, path, ec);
    PS_CHECK(!ec, "{}: cannot move {} into place: {}", path.string(), tmp.string(), ec.message());
  } catch (...) {
    std::error_code ignored;
    fs::remove(tmp, ignored);
    throw;
  }
}

void write_file_atomic(const fs::path& path, const void* data, size_t size) {
  write_file_atomic(path, [&](std::ostream& out) {
    out.write(static_cast<const char*>(data), static_cast<std::streamsize>(size));
  });
}

std::string lower_extension(const fs::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
  return ext;
}

}  // namespace pillarseg
