#include "engine/data/cache.hpp"

#include <fmt/format.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <ostream>

#include "core/error.hpp"
#include "core/io.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

namespace {

constexpr char kMagic[8] = {'P', 'S', 'C', 'A', 'C', 'H', 'E', '1'};
constexpr uint32_t kContainerVersion = 1;
constexpr uint32_t kMaxRank = 8;

uint64_t checksum(const char* data, size_t size) {
  Hasher h;
  h.add_bytes(data, size);
  return h.digest();
}

template <class T>
void put(std::ostream& out, T value) {
  out.write(reinterpret_cast<const char*>(&value), sizeof value);
}

// Sequential reader over a file's bytes; every read checks that the bytes are there.
class ByteReader {
 public:
  explicit ByteReader(const std::vector<char>& bytes) : bytes_(bytes) {}
  template <class T>
  bool get(T& value) {
    if (remaining() < sizeof value) return false;
    std::memcpy(&value, bytes_.data() + pos_, sizeof value);
    pos_ += sizeof value;
    return true;
  }
  bool get_text(size_t size, std::string& text) {
    if (remaining() < size) return false;
    text.assign(bytes_.data() + pos_, size);
    pos_ += size;
    return true;
  }
  size_t position() const { return pos_; }
  size_t remaining() const { return bytes_.size() - pos_; }

 private:
  const std::vector<char>& bytes_;
  size_t pos_ = 0;
};

bool writable_dir(const fs::path& dir) {
  std::error_code ec;
  return fs::is_directory(dir, ec) && ::access(dir.c_str(), W_OK | X_OK) == 0;
}

}  // namespace

std::string CacheKey::text() const {
  return fmt::format("sequence={}\nframe={}\nkind={}\nsettings={:016x}\ninputs={:016x}\n", sequence,
                     frame, kind, settings, inputs);
}

void hash_file_stamp(Hasher& h, const fs::path& file) {
  std::error_code size_error, time_error;
  const uintmax_t size = fs::file_size(file, size_error);
  const fs::file_time_type mtime = fs::last_write_time(file, time_error);
  if (size_error || time_error) {
    h.add(~uint64_t{0});
    return;
  }
  h.add(static_cast<uint64_t>(size));
  h.add(static_cast<int64_t>(mtime.time_since_epoch().count()));
}

fs::path default_cache_dir(const fs::path& data_root) {
  const fs::path beside_data = data_root / "pillarseg_cache";
  std::error_code ec;
  if (fs::exists(beside_data, ec) ? writable_dir(beside_data) : writable_dir(data_root))
    return beside_data;
  if (const char* xdg = std::getenv("XDG_CACHE_HOME"); xdg && *xdg)
    return fs::path(xdg) / "pillarseg";
  const char* home = std::getenv("HOME");
  PS_CHECK(home && *home,
           "no cache directory: {} is not writable and neither XDG_CACHE_HOME nor HOME is set; "
           "pass --cache DIR",
           data_root.string());
  return fs::path(home) / ".cache" / "pillarseg";
}

Cache::Cache(fs::path dir) : dir_(std::move(dir)) {
  PS_CHECK(!dir_.empty(), "cache directory: expected a path, got an empty one");
}

fs::path Cache::path_of(const CacheKey& key) const {
  PS_CHECK(!key.kind.empty() && std::all_of(key.kind.begin(), key.kind.end(),
                                            [](char c) {
                                              return (c >= 'a' && c <= 'z') ||
                                                     (c >= '0' && c <= '9') || c == '-';
                                            }),
           "cache key kind '{}': expected lower-case letters, digits and '-'", key.kind);
  PS_CHECK(key.frame >= 0, "cache key frame {}: expected a frame number >= 0", key.frame);
  return sequence_dir(key.sequence) / key.kind / fmt::format("{:06}-{:016x}.psc", key.frame, key.settings);
}

fs::path Cache::sequence_dir(const std::string& sequence) const {
  Hasher sequence_hash;
  sequence_hash.add(sequence);
  std::string name = fs::path(sequence).filename().string();
  if (name.empty()) name = "sequence";
  return dir_ / fmt::format("{}-{:08x}", name, sequence_hash.digest() & 0xFFFFFFFFu);
}

size_t Cache::remove_stale_temporaries(const std::string& sequence) const {
  const fs::path dir = sequence_dir(sequence);
  const size_t removed = pillarseg::remove_stale_temporaries(dir, /*recursive=*/true);
  if (removed > 0)
    spdlog::info("cache: removed {} temporary file(s) that killed writers left in {}", removed, dir.string());
  return removed;
}

std::optional<Cache::Entry> Cache::read_entry(const CacheKey& key, CacheDType dtype,
                                              size_t element_size) const {
  const fs::path path = path_of(key);
  std::error_code ec;
  if (!fs::is_regular_file(path, ec)) return std::nullopt;
  Entry entry;
  try {
    entry.file = read_file_bytes(path);
  } catch (const Error& e) {
    spdlog::warn("cache: {}; treating it as a miss", e.what());
    return std::nullopt;
  }
  const auto corrupt = [&](const char* what) -> std::optional<Entry> {
    spdlog::warn("cache: {} is corrupt ({}); treating it as a miss", path.string(), what);
    return std::nullopt;
  };

  ByteReader in(entry.file);
  char magic[sizeof kMagic];
  uint32_t version = 0, key_bytes = 0;
  std::string key_text;
  if (!in.get(magic) || std::memcmp(magic, kMagic, sizeof kMagic) != 0)
    return corrupt("no PSCACHE1 magic");
  if (!in.get(version)) return corrupt("truncated header");
  if (version != kContainerVersion) {
    spdlog::debug("cache: {} has container version {}, expected {}", path.string(), version,
                  kContainerVersion);
    return std::nullopt;
  }
  if (!in.get(key_bytes) || !in.get_text(key_bytes, key_text)) return corrupt("truncated key");
  if (key_text != key.text()) {
    spdlog::debug("cache: {} holds another key (inputs or settings changed)", path.string());
    return std::nullopt;
  }
  uint32_t stored_dtype = 0, rank = 0;
  if (!in.get(stored_dtype) || !in.get(rank)) return corrupt("truncated header");
  if (stored_dtype != static_cast<uint32_t>(dtype)) {
    spdlog::debug("cache: {} holds dtype {}, asked for {}", path.string(), stored_dtype,
                  static_cast<uint32_t>(dtype));
    return std::nullopt;
  }
  if (rank > kMaxRank) return corrupt("rank too large");
  uint64_t numel = 1;
  for (uint32_t d = 0; d < rank; ++d) {
    int64_t dim = 0;
    if (!in.get(dim)) return corrupt("truncated shape");
    if (dim < 0) return corrupt("negative dimension");
    // numel stays <= the file size, so the product cannot overflow.
    if (dim > 0 && numel > entry.file.size() / static_cast<uint64_t>(dim))
      return corrupt("shape larger than the file");
    numel *= static_cast<uint64_t>(dim);
    entry.shape.push_back(dim);
  }
  uint64_t payload_bytes = 0, payload_checksum = 0;
  if (!in.get(payload_bytes) || !in.get(payload_checksum)) return corrupt("truncated header");
  if (payload_bytes != numel * element_size)
    return corrupt("payload size does not match the shape");
  if (in.remaining() != payload_bytes) return corrupt("file size does not match the payload size");
  entry.payload_offset = in.position();
  if (checksum(entry.file.data() + entry.payload_offset, payload_bytes) != payload_checksum)
    return corrupt("payload checksum mismatch");
  return entry;
}

void Cache::write_entry(const CacheKey& key, CacheDType dtype, const Shape& shape, const void* data,
                        size_t bytes) const {
  PS_CHECK(shape.size() <= kMaxRank, "cache store {}: rank {} exceeds {}", key.kind, shape.size(),
           kMaxRank);
  const std::string key_text = key.text();
  const char* payload = static_cast<const char*>(data);
  write_file_atomic(path_of(key), [&](std::ostream& out) {
    out.write(kMagic, sizeof kMagic);
    put(out, kContainerVersion);
    put(out, static_cast<uint32_t>(key_text.size()));
    out.write(key_text.data(), static_cast<std::streamsize>(key_text.size()));
    put(out, static_cast<uint32_t>(dtype));
    put(out, static_cast<uint32_t>(shape.size()));
    for (int64_t dim : shape) put(out, dim);
    put(out, static_cast<uint64_t>(bytes));
    put(out, checksum(payload, bytes));
    out.write(payload, static_cast<std::streamsize>(bytes));
  });
}

std::optional<std::vector<char>> Cache::load_bytes(const CacheKey& key) const {
  std::optional<Entry> entry = read_entry(key, CacheDType::bytes, 1);
  if (!entry) return std::nullopt;
  if (entry->shape.size() != 1) {
    spdlog::warn("cache: {} holds a blob of rank {}, expected 1; treating it as a miss",
                 path_of(key).string(), entry->shape.size());
    return std::nullopt;
  }
  return std::vector<char>(entry->file.begin() + static_cast<std::ptrdiff_t>(entry->payload_offset),
                           entry->file.end());
}

void Cache::store_bytes(const CacheKey& key, std::span<const char> bytes) const {
  write_entry(key, CacheDType::bytes, Shape{static_cast<int64_t>(bytes.size())}, bytes.data(),
              bytes.size());
}

}  // namespace pillarseg
