#include "core/memory_budget.hpp"

#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cstdlib>
#include <fstream>
#include <iterator>
#include <sstream>
#include <vector>

#include "core/error.hpp"

namespace pillarseg {

namespace {

// A limit of 2^60 bytes or more is no limit (cgroup v1 writes 2^63 - 4096 for "none").
constexpr uint64_t kNoLimit = uint64_t{1} << 60;

std::string_view trim(std::string_view s) {
  while (!s.empty() && std::isspace(static_cast<unsigned char>(s.front()))) s.remove_prefix(1);
  while (!s.empty() && std::isspace(static_cast<unsigned char>(s.back()))) s.remove_suffix(1);
  return s;
}

std::optional<uint64_t> parse_u64(std::string_view s) {
  s = trim(s);
  uint64_t value = 0;
  const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
  if (s.empty() || ec != std::errc() || ptr != s.data() + s.size()) return std::nullopt;
  return value;
}

// The whole of a small file (/proc, /sys), or nothing when it cannot be read.
std::optional<std::string> read_small_file(const std::string& path) {
  std::ifstream in(path);
  if (!in) return std::nullopt;
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

// The number after `key` in a file of "key value" lines (/proc/meminfo "MemAvailable: 123 kB",
// cgroup memory.stat "inactive_file 123"), times `unit`.
std::optional<uint64_t> keyed_value(const std::string& path, std::string_view key, uint64_t unit) {
  const std::optional<std::string> text = read_small_file(path);
  if (!text) return std::nullopt;
  std::istringstream lines(*text);
  std::string line;
  while (std::getline(lines, line)) {
    std::string_view l(line);
    if (l.substr(0, key.size()) != key) continue;
    l.remove_prefix(key.size());
    if (!l.empty() && l.front() == ':')
      l.remove_prefix(1);
    else if (l.empty() || !std::isspace(static_cast<unsigned char>(l.front())))
      continue;  // a longer key
    if (const size_t kb = l.find("kB"); kb != std::string_view::npos) l = l.substr(0, kb);
    if (const std::optional<uint64_t> v = parse_u64(l)) return *v * unit;
    return std::nullopt;
  }
  return std::nullopt;
}

// One bound on what may be allocated.
struct Bound {
  uint64_t bytes = 0;
  std::string description;
};

// The tightest cgroup bound: this process's memory cgroup and each one above it (v2, or v1's
// memory controller), limit - usage + inactive page cache.
std::optional<Bound> cgroup_bound() {
  const std::optional<std::string> self = read_small_file("/proc/self/cgroup");
  if (!self) return std::nullopt;
  std::string v2_path, v1_path;
  bool has_v2 = false, has_v1 = false;
  std::istringstream lines(*self);
  std::string line;
  while (std::getline(lines, line)) {
    // "hierarchy-id:controllers:path"
    const size_t a = line.find(':'), b = a == std::string::npos ? a : line.find(':', a + 1);
    if (b == std::string::npos) continue;
    const std::string id = line.substr(0, a), controllers = line.substr(a + 1, b - a - 1);
    const std::string path = line.substr(b + 1);
    if (id == "0" && controllers.empty()) {
      has_v2 = true, v2_path = path;
    } else {
      std::istringstream names(controllers);
      std::string name;
      while (std::getline(names, name, ','))
        if (name == "memory") has_v1 = true, v1_path = path;
    }
  }
  struct Layout {
    std::string mount, path, limit_file, usage_file, inactive_key;
  };
  std::vector<Layout> layouts;
  if (has_v1)
    layouts.push_back({"/sys/fs/cgroup/memory", v1_path, "memory.limit_in_bytes",
                       "memory.usage_in_bytes", "total_inactive_file"});
  if (has_v2) {
    const bool unified_root = read_small_file("/sys/fs/cgroup/cgroup.controllers").has_value();
    layouts.push_back({unified_root ? "/sys/fs/cgroup" : "/sys/fs/cgroup/unified", v2_path,
                       "memory.max", "memory.current", "inactive_file"});
  }
  std::optional<Bound> best;
  for (const Layout& layout : layouts) {
    // The cgroup's directory and each one above it up to the mount (a cgroup namespace shows
    // its own cgroup as the mount itself: then only the mount's files are read).
    std::string path = layout.path;
    while (true) {
      const std::string dir = layout.mount + (path == "/" ? "" : path);
      const std::optional<std::string> limit_text = read_small_file(dir + "/" + layout.limit_file);
      const std::optional<uint64_t> limit =
          limit_text ? parse_u64(*limit_text) : std::nullopt;  // "max": none
      if (limit && *limit < kNoLimit) {
        const std::optional<std::string> usage_text =
            read_small_file(dir + "/" + layout.usage_file);
        const uint64_t usage = usage_text ? parse_u64(*usage_text).value_or(0) : 0;
        const uint64_t inactive =
            keyed_value(dir + "/memory.stat", layout.inactive_key, 1).value_or(0);
        const uint64_t used = usage > inactive ? usage - inactive : 0;
        const uint64_t headroom = used < *limit ? *limit - used : 0;
        if (!best || headroom < best->bytes) {
          best = Bound{headroom, fmt::format("cgroup {} limit {}, {} of it free", path,
                                             format_bytes(*limit), format_bytes(headroom))};
        }
      }
      if (path.empty() || path == "/") break;
      const size_t slash = path.rfind('/');
      path = slash == 0 || slash == std::string::npos ? "/" : path.substr(0, slash);
    }
  }
  return best;
}

// RLIMIT_AS (against VmSize) or RLIMIT_DATA (against VmData), when set.
std::optional<Bound> rlimit_bound(int resource, const char* name, const char* status_key) {
  rlimit limit{};
  if (getrlimit(resource, &limit) != 0 || limit.rlim_cur == RLIM_INFINITY) return std::nullopt;
  const uint64_t cap = limit.rlim_cur;
  const uint64_t used = keyed_value("/proc/self/status", status_key, 1024).value_or(0);
  const uint64_t headroom = used < cap ? cap - used : 0;
  return Bound{headroom, fmt::format("{} {}, {} of it free", name, format_bytes(cap),
                                     format_bytes(headroom))};
}

}  // namespace

std::optional<MemoryBudget> memory_limit_override() {
  const char* env = std::getenv("PILLARSEG_MEMORY_LIMIT");
  if (env == nullptr || *env == '\0') return std::nullopt;
  std::string_view text = trim(env);
  uint64_t value = 0;
  const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  std::string_view suffix =
      ec == std::errc() ? std::string_view(ptr, text.data() + text.size() - ptr) : "";
  int shift = -1;
  if (ec == std::errc()) {
    if (suffix.empty())
      shift = 0;
    else {
      const char unit = static_cast<char>(std::toupper(static_cast<unsigned char>(suffix.front())));
      const std::string_view rest = suffix.substr(1);
      const size_t at = std::string_view("KMGT").find(unit);
      if (at != std::string_view::npos &&
          (rest.empty() || rest == "B" || rest == "iB" || rest == "b"))
        shift = 10 * static_cast<int>(at + 1);
    }
  }
  PS_CHECK(shift >= 0 && (shift == 0 || value <= (~uint64_t{0} >> shift)),
           "PILLARSEG_MEMORY_LIMIT='{}': expected a byte count such as 8589934592, or 512M, 8G "
           "(powers of 1024)",
           env);
  const uint64_t bytes = value << shift;
  return MemoryBudget{bytes, fmt::format("PILLARSEG_MEMORY_LIMIT={}", env)};
}

MemoryBudget host_memory_budget() {
  if (std::optional<MemoryBudget> forced = memory_limit_override()) return *forced;
  const long pages = sysconf(_SC_PHYS_PAGES), page_size = sysconf(_SC_PAGE_SIZE);
  const uint64_t physical = pages > 0 && page_size > 0
                                ? static_cast<uint64_t>(pages) * static_cast<uint64_t>(page_size)
                                : 0;
  std::vector<Bound> bounds;
  if (const std::optional<uint64_t> available =
          keyed_value("/proc/meminfo", "MemAvailable", 1024)) {
    bounds.push_back({*available, fmt::format("MemAvailable {} of {} RAM", format_bytes(*available),
                                              format_bytes(physical))});
  } else if (physical > 0) {
    bounds.push_back({physical, fmt::format("{} RAM", format_bytes(physical))});
  }
  if (std::optional<Bound> b = cgroup_bound()) bounds.push_back(std::move(*b));
  if (std::optional<Bound> b = rlimit_bound(RLIMIT_AS, "RLIMIT_AS", "VmSize"))
    bounds.push_back(std::move(*b));
  if (std::optional<Bound> b = rlimit_bound(RLIMIT_DATA, "RLIMIT_DATA", "VmData"))
    bounds.push_back(std::move(*b));
  MemoryBudget budget;
  budget.bytes = ~uint64_t{0};
  for (const Bound& b : bounds) {
    budget.bytes = std::min(budget.bytes, b.bytes);
    budget.description += (budget.description.empty() ? "" : "; ") + b.description;
  }
  if (bounds.empty()) budget.description = "the machine's memory could not be read: no limit";
  return budget;
}

void require_memory(uint64_t bytes, std::string_view what, const MemoryBudget& budget) {
  PS_CHECK(bytes <= budget.bytes, "{} would need {}, more than the {} of memory available ({})",
           what, format_bytes(bytes), format_bytes(budget.bytes), budget.description);
}

void require_memory(uint64_t bytes, std::string_view what) {
  require_memory(bytes, what, host_memory_budget());
}

std::string format_bytes(uint64_t bytes) {
  if (bytes < 1024) return fmt::format("{} B", bytes);
  static constexpr const char* kUnits[] = {"KiB", "MiB", "GiB", "TiB", "PiB", "EiB"};
  double value = static_cast<double>(bytes) / 1024.0;
  size_t unit = 0;
  while (value >= 1023.95 && unit + 1 < std::size(kUnits)) value /= 1024.0, ++unit;
  return fmt::format("{:.1f} {}", value, kUnits[unit]);
}

uint64_t checked_product(std::initializer_list<int64_t> factors, std::string_view what) {
  const auto spelled = [&] {
    std::string s;
    for (const int64_t f : factors) s += (s.empty() ? "" : " x ") + std::to_string(f);
    return s;
  };
  uint64_t product = 1;
  for (const int64_t f : factors) {
    PS_CHECK(f >= 0, "{}: {} has a negative factor", what, spelled());
    PS_CHECK(!__builtin_mul_overflow(product, static_cast<uint64_t>(f), &product),
             "{}: {} overflows 64-bit arithmetic", what, spelled());
  }
  return product;
}

uint64_t checked_sum(std::initializer_list<uint64_t> terms, std::string_view what) {
  uint64_t sum = 0;
  for (const uint64_t t : terms) {
    PS_CHECK(!__builtin_add_overflow(sum, t, &sum),
             "{}: the sum of {} sizes overflows 64-bit arithmetic", what, terms.size());
  }
  return sum;
}

void require_int32_count(std::initializer_list<int64_t> factors, std::string_view what,
                         std::string_view indices) {
  for (const int64_t f : factors) {
    PS_CHECK(f >= 0, "{}: a count must be >= 0, given {}", what, f);
    if (f == 0) return;
  }
  // In 128 bits, saturating, so that the message prints the product however large it is
  // (__extension__: GCC's and clang's 128-bit integer, which ISO C++ does not name).
  __extension__ typedef unsigned __int128 U128;
  constexpr auto kSaturated = ~static_cast<U128>(0);
  U128 product = 1;
  for (const int64_t f : factors) {
    const auto factor = static_cast<U128>(f);
    product = product > kSaturated / factor ? kSaturated : product * factor;
  }
  if (product <= static_cast<U128>(kMaxInt32Index)) return;
  const std::string count = product <= ~uint64_t{0}
                                ? std::to_string(static_cast<uint64_t>(product))
                                : fmt::format("{:.3g}", static_cast<long double>(product));
  PS_FAIL("{} = {} overflows the 32-bit {} (at most {})", what, count, indices, kMaxInt32Index);
}

}  // namespace pillarseg
