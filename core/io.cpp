#include "core/io.hpp"

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <sstream>

#include <fcntl.h>
#include <signal.h>
#include <unistd.h>

#include <cctype>
#include <charconv>
#include <streambuf>
#include <string_view>

#include "core/error.hpp"
#include "core/fault.hpp"

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

namespace {

// This host's name as it appears in temporary file names: [A-Za-z0-9_.] only.
const std::string& host_tag() {
  static const std::string tag = [] {
    char name[256] = {};
    if (::gethostname(name, sizeof name - 1) != 0 || name[0] == '\0') return std::string("host");
    std::string out(name);
    for (char& c : out) {
      if (!std::isalnum(static_cast<unsigned char>(c)) && c != '.' && c != '_') c = '_';
    }
    return out;
  }();
  return tag;
}

// A stream buffer on a file descriptor that writes with ::write, keeps the first error's errno
// and then refuses further output (the stream goes bad), and reaches the fault point
// "write:NAME" after each batch of bytes that reached the file.
class FdWriteBuffer : public std::streambuf {
 public:
  FdWriteBuffer(int fd, std::string fault_name) : fd_(fd), fault_(std::move(fault_name)), buffer_(kBufferBytes) {
    setp(buffer_.data(), buffer_.data() + buffer_.size());
  }
  int error() const { return error_; }

 protected:
  int_type overflow(int_type ch) override {
    if (!drain()) return traits_type::eof();
    if (traits_type::eq_int_type(ch, traits_type::eof())) return traits_type::not_eof(ch);
    *pptr() = traits_type::to_char_type(ch);
    pbump(1);
    return ch;
  }
  std::streamsize xsputn(const char* s, std::streamsize n) override {
    if (n < static_cast<std::streamsize>(buffer_.size())) return std::streambuf::xsputn(s, n);
    if (!drain() || !write_all(s, static_cast<size_t>(n))) return 0;
    return n;
  }
  int sync() override { return drain() ? 0 : -1; }

 private:
  static constexpr size_t kBufferBytes = size_t{1} << 20;

  bool drain() {
    const bool ok = write_all(pbase(), static_cast<size_t>(pptr() - pbase()));
    setp(buffer_.data(), buffer_.data() + buffer_.size());
    return ok;
  }
  bool write_all(const char* data, size_t size) {
    if (error_ != 0) return false;
    if (size == 0) return true;
    while (size > 0) {
      const ssize_t n = ::write(fd_, data, size);
      if (n < 0) {
        if (errno == EINTR) continue;
        error_ = errno;
        return false;
      }
      data += n;
      size -= static_cast<size_t>(n);
    }
    fault_point(fault_);
    return true;
  }

  int fd_;
  std::string fault_;
  std::vector<char> buffer_;
  int error_ = 0;
};

void sync_directory(const fs::path& dir, const fs::path& target) {
  const int fd = ::open(dir.empty() ? "." : dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  PS_CHECK(fd >= 0, "{}: cannot open its directory to sync it: {}", target.string(), std::strerror(errno));
  const int rc = ::fsync(fd);
  const int err = errno;
  ::close(fd);
  PS_CHECK(rc == 0 || err == EINVAL, "{}: cannot sync its directory: {}", target.string(), write_error_cause(err));
}

// Whether `pid` names a process that can still write: one that exists (or that we may not
// signal) and is not a zombie (killed, not yet reaped - its parent gone too, in a container
// whose init does not reap).
bool process_runs(pid_t pid) {
  if (::kill(pid, 0) != 0 && errno == ESRCH) return false;
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string line;
  if (!std::getline(stat, line)) return true;
  const size_t name_end = line.rfind(')');  // "pid (name) state ..."; the name may hold anything
  return name_end == std::string::npos || name_end + 2 >= line.size() ||
         (line[name_end + 2] != 'Z' && line[name_end + 2] != 'X');
}

}  // namespace

std::string write_error_cause(int err) {
  if (err == ENOSPC || err == EDQUOT) return "no space left on device (the file system or the quota is full)";
  return std::strerror(err);
}

void write_file_atomic(const fs::path& path, const std::function<void(std::ostream&)>& write, Durability durability) {
  static std::atomic<uint64_t> counter{0};
  if (path.has_parent_path()) {
    std::error_code ec;
    fs::create_directories(path.parent_path(), ec);
    PS_CHECK(!ec, "{}: cannot create directory {}: {}", path.string(), path.parent_path().string(),
             ec.message());
  }
  const fs::path tmp = fmt::format("{}.tmp-{}-{}-{}", path.string(), host_tag(), ::getpid(), counter.fetch_add(1));
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
  PS_CHECK(fd >= 0, "{}: cannot create {}: {}", path.string(), tmp.string(), write_error_cause(errno));
  bool open = true;
  try {
    int err = 0;
    {
      FdWriteBuffer buffer(fd, "write:" + path.filename().string());
      std::ostream out(&buffer);
      write(out);
      out.flush();
      err = buffer.error();
      PS_CHECK(err == 0 && out.good(), "{}: cannot write it: {}; the file is unchanged", path.string(),
               err != 0 ? write_error_cause(err) : std::string("the stream failed"));
    }
    if (durability == Durability::kPowerLoss && ::fsync(fd) != 0)
      PS_FAIL("{}: cannot sync it to disk: {}; the file is unchanged", path.string(), write_error_cause(errno));
    const int closed = ::close(fd);
    open = false;  // whatever close returned: the descriptor is released
    PS_CHECK(closed == 0, "{}: cannot write it (close): {}; the file is unchanged", path.string(), write_error_cause(errno));
  } catch (...) {
    if (open) ::close(fd);
    std::error_code ignored;
    fs::remove(tmp, ignored);
    throw;
  }
  std::error_code ec;
  fs::rename(tmp, path, ec);
  if (ec) {
    std::error_code ignored;
    fs::remove(tmp, ignored);
    PS_FAIL("{}: cannot move {} into place: {}", path.string(), tmp.string(), ec.message());
  }
  if (durability == Durability::kPowerLoss) sync_directory(path.parent_path(), path);
}

void write_file_atomic(const fs::path& path, const void* data, size_t size, Durability durability) {
  write_file_atomic(
      path,
      [&](std::ostream& out) { out.write(static_cast<const char*>(data), static_cast<std::streamsize>(size)); },
      durability);
}

size_t remove_stale_temporaries(const fs::path& dir, bool recursive) {
  // NAME.tmp-HOST-PID-N with this host's HOST and a PID that no longer runs.
  const std::string marker = ".tmp-" + host_tag() + "-";
  size_t removed = 0;
  const auto consider = [&](const fs::directory_entry& entry) {
    std::error_code ec;
    if (!entry.is_regular_file(ec)) return;
    const std::string name = entry.path().filename().string();
    const size_t at = name.rfind(marker);
    if (at == std::string::npos) return;
    const std::string_view rest = std::string_view(name).substr(at + marker.size());
    const size_t dash = rest.find('-');
    if (dash == std::string_view::npos) return;
    long long pid = 0, n = 0;
    const std::string_view pid_text = rest.substr(0, dash), n_text = rest.substr(dash + 1);
    const auto p = std::from_chars(pid_text.data(), pid_text.data() + pid_text.size(), pid);
    const auto q = std::from_chars(n_text.data(), n_text.data() + n_text.size(), n);
    if (p.ec != std::errc() || p.ptr != pid_text.data() + pid_text.size() || q.ec != std::errc() ||
        q.ptr != n_text.data() + n_text.size() || pid <= 0)
      return;
    if (process_runs(static_cast<pid_t>(pid))) return;
    if (fs::remove(entry.path(), ec)) ++removed;
  };
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return 0;
  if (recursive) {
    for (fs::recursive_directory_iterator it(dir, fs::directory_options::skip_permission_denied, ec), end;
         !ec && it != end; it.increment(ec))
      consider(*it);
  } else {
    for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) consider(*it);
  }
  return removed;
}

std::string lower_extension(const fs::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
  return ext;
}

}  // namespace pillarseg
