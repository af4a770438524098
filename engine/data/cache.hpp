// On-disk cache of per-scan maps (ground truth, observability, occupancy, aggregated point
// sets): one file per (sequence, frame, kind, settings), so that training does not rebuild
// them every epoch.
//
// A CacheKey names what a file holds: the sequence directory (canonical path), the frame
// number, the kind ("gt-sparse", "gt-dense", ...), `settings`, a hash of everything the
// content is computed with (grid, class table, kind parameters, a format version), and
// `inputs`, a hash of the sizes and modification times of the input files it was computed
// from. The file name carries the sequence, kind, frame and settings; the header carries the
// whole key. A file whose header key differs (an input file was rewritten, or a name clash),
// whose dtype or shape does not fit, or which is truncated or corrupt (payload checksum) is a
// miss, never trusted; the next store overwrites it. Writes are atomic (temporary file, then
// rename), so readers never see half a file, even with several writers.
//
// File layout (little-endian):
//   "PSCACHE1" | u32 container version | u32 key bytes | key text | u32 dtype | u32 rank |
//   i64 dims[rank] | u64 payload bytes | u64 FNV-1a of the payload | payload (row-major)
#pragma once

#include <cstdint>
#include <cstring>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <type_traits>
#include <vector>

#include "core/hash.hpp"
#include "core/tensor.hpp"

namespace pillarseg {

struct CacheKey {
  std::string sequence;   // canonical path of the sequence directory
  int frame = 0;          // NNNNNN of the scan's file name
  std::string kind;       // what is stored: [a-z0-9-]+, e.g. "gt-sparse"
  uint64_t settings = 0;  // hash of the computation's settings (part of the file name)
  uint64_t inputs = 0;    // hash of the input files' sizes and mtimes (header only)

  // The text stored in the header and compared on load.
  std::string text() const;
  bool operator==(const CacheKey&) const = default;
};

// Element types a cache file can hold; `bytes` is an untyped blob of rank 1.
enum class CacheDType : uint32_t { u8 = 1, u16, u32, i32, i64, f32, f64, bytes };

template <class T>
constexpr CacheDType cache_dtype() {
  if constexpr (std::is_same_v<T, uint8_t>)
    return CacheDType::u8;
  else if constexpr (std::is_same_v<T, uint16_t>)
    return CacheDType::u16;
  else if constexpr (std::is_same_v<T, uint32_t>)
    return CacheDType::u32;
  else if constexpr (std::is_same_v<T, int32_t>)
    return CacheDType::i32;
  else if constexpr (std::is_same_v<T, int64_t>)
    return CacheDType::i64;
  else if constexpr (std::is_same_v<T, float>)
    return CacheDType::f32;
  else if constexpr (std::is_same_v<T, double>)
    return CacheDType::f64;
  else
    static_assert(sizeof(T) == 0, "no cache dtype for this element type");
}

// Adds the size and modification time of `file` to h (a marker when it does not exist), so
// that rewriting or touching an input file changes the key of everything made from it.
void hash_file_stamp(Hasher& h, const std::filesystem::path& file);

// `<data_root>/pillarseg_cache` when that directory (or, if it does not exist yet, data_root)
// is writable; otherwise `$XDG_CACHE_HOME/pillarseg`, or `~/.cache/pillarseg` without it.
std::filesystem::path default_cache_dir(const std::filesystem::path& data_root);

class Cache {
 public:
  explicit Cache(std::filesystem::path dir);

  const std::filesystem::path& dir() const { return dir_; }
  // dir/<sequence name>-<hash of its path>/<kind>/<frame:06>-<settings:016x>.psc
  std::filesystem::path path_of(const CacheKey& key) const;
  // dir/<sequence name>-<hash of its path>: the entries of the sequence at that canonical path.
  std::filesystem::path sequence_dir(const std::string& sequence) const;
  // Removes the temporary files that killed writers on this host left among the sequence's
  // entries (remove_stale_temporaries, core/io.hpp); a live writer's are kept.
  size_t remove_stale_temporaries(const std::string& sequence) const;

  // The stored tensor, or nullopt on a miss (no file, other key, other dtype, corrupt).
  template <class T>
  std::optional<Tensor<T>> load(const CacheKey& key) const {
    std::optional<Entry> entry = read_entry(key, cache_dtype<T>(), sizeof(T));
    if (!entry) return std::nullopt;
    Tensor<T> tensor(entry->shape);
    if (tensor.numel() > 0)
      std::memcpy(tensor.data(), entry->file.data() + entry->payload_offset,
                  static_cast<size_t>(tensor.numel()) * sizeof(T));
    return tensor;
  }
  template <class T>
  void store(const CacheKey& key, const Tensor<T>& tensor) const {
    write_entry(key, cache_dtype<T>(), tensor.shape(), tensor.data(),
                static_cast<size_t>(tensor.numel()) * sizeof(T));
  }

  // Untyped blobs (e.g. a serialised point set).
  std::optional<std::vector<char>> load_bytes(const CacheKey& key) const;
  void store_bytes(const CacheKey& key, std::span<const char> bytes) const;

 private:
  struct Entry {
    std::vector<char> file;  // the whole file
    Shape shape;
    size_t payload_offset = 0;
  };
  std::optional<Entry> read_entry(const CacheKey& key, CacheDType dtype, size_t element_size) const;
  void write_entry(const CacheKey& key, CacheDType dtype, const Shape& shape, const void* data,
                   size_t bytes) const;

  std::filesystem::path dir_;
};

}  // namespace pillarseg
