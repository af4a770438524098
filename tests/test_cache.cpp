// On-disk cache: round trips of every dtype and of blobs, misses on any key change (settings,
// an input file rewritten or touched, another dtype), corrupt and truncated files read as
// misses (never an exception) and get rewritten, atomic writes, the default directory.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <limits>
#include <optional>
#include <string>

#include "core/hash.hpp"
#include "core/io.hpp"
#include "engine/data/cache.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
namespace fs = std::filesystem;

namespace {

CacheKey sample_key() {
  return CacheKey{"/data/sequences/08", 123, "gt-sparse", 0x1234, 0xABCD};
}

template <class T>
Tensor<T> ramp(Shape shape) {
  Tensor<T> t(std::move(shape));
  for (int64_t i = 0; i < t.numel(); ++i) t[i] = static_cast<T>(i * 7 % 251);
  return t;
}

void write_bytes(const fs::path& path, const std::vector<char>& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

}  // namespace

TEST(Cache, RoundTripsEveryDtype) {
  const Cache cache(test::temp_dir());
  CacheKey key = sample_key();
  const auto check = [&](const auto& tensor, const char* kind) {
    using T = std::decay_t<decltype(tensor[0])>;
    key.kind = kind;
    cache.store(key, tensor);
    const std::optional<Tensor<T>> back = cache.load<T>(key);
    ASSERT_TRUE(back) << kind;
    EXPECT_EQ(back->shape(), tensor.shape()) << kind;
    EXPECT_EQ(back->values(), tensor.values()) << kind;
  };
  check(ramp<uint8_t>({5, 7}), "u8");
  check(ramp<uint16_t>({3, 4, 5}), "u16");
  check(ramp<uint32_t>({11}), "u32");
  check(ramp<int32_t>({2, 2}), "i32");
  check(ramp<int64_t>({1, 3}), "i64");
  check(ramp<double>({4, 1}), "f64");
  check(Tensor<uint8_t>({0, 9}), "empty");
  check(Tensor<float>(Shape{}, 2.5f), "scalar");
  // Floats bit for bit, NaN and infinities included.
  Tensor<float> special({4});
  special[0] = NAN, special[1] = INFINITY, special[2] = -0.0f, special[3] = 1e-42f;
  key.kind = "f32";
  cache.store(key, special);
  const auto back = cache.load<float>(key);
  ASSERT_TRUE(back);
  EXPECT_TRUE(std::isnan((*back)[0]));
  EXPECT_EQ((*back)[1], INFINITY);
  EXPECT_TRUE(std::signbit((*back)[2]));
  EXPECT_EQ((*back)[3], 1e-42f);
}

TEST(Cache, BlobsRoundTrip) {
  const Cache cache(test::temp_dir());
  CacheKey key = sample_key();
  key.kind = "points";
  const std::vector<char> blob = {'a', '\0', 'b', static_cast<char>(0xFF)};
  cache.store_bytes(key, blob);
  EXPECT_EQ(cache.load_bytes(key), blob);
  cache.store_bytes(key, {});
  EXPECT_EQ(cache.load_bytes(key), std::vector<char>{});
  // A blob is not a tensor and vice versa.
  EXPECT_FALSE(cache.load<uint8_t>(key));
  cache.store(key, ramp<uint8_t>({4}));
  EXPECT_FALSE(cache.load_bytes(key));
}

TEST(Cache, FileNameAndHeaderCarryTheKey) {
  const fs::path dir = test::temp_dir();
  const Cache cache(dir);
  const CacheKey key = sample_key();
  const fs::path path = cache.path_of(key);
  EXPECT_EQ(path.parent_path().filename(), "gt-sparse");
  EXPECT_EQ(path.filename(), "000123-0000000000001234.psc");
  EXPECT_EQ(path.parent_path().parent_path().filename().string().substr(0, 3), "08-");
  EXPECT_EQ(key.text(),
            "sequence=/data/sequences/08\nframe=123\nkind=gt-sparse\nsettings=0000000000001234\n"
            "inputs=000000000000abcd\n");
  cache.store(key, ramp<uint8_t>({2, 3}));
  const std::vector<char> bytes = read_file_bytes(path);
  ASSERT_GT(bytes.size(), 16u);
  EXPECT_EQ(std::string(bytes.data(), 8), "PSCACHE1");
  EXPECT_NE(std::string(bytes.begin(), bytes.end()).find(key.text()), std::string::npos);

  CacheKey bad = key;
  bad.kind = "../escape";
  EXPECT_THROW(cache.path_of(bad), Error);
  bad.kind = "";
  EXPECT_THROW(cache.path_of(bad), Error);
  EXPECT_THROW(Cache(""), Error);
}

TEST(Cache, AnyKeyChangeIsAMiss) {
  const Cache cache(test::temp_dir());
  const CacheKey key = sample_key();
  EXPECT_FALSE(cache.load<uint8_t>(key));  // nothing stored yet
  cache.store(key, ramp<uint8_t>({3, 3}));
  ASSERT_TRUE(cache.load<uint8_t>(key));

  CacheKey other = key;
  other.settings ^= 1;  // e.g. another grid or class table: another file
  EXPECT_NE(cache.path_of(other), cache.path_of(key));
  EXPECT_FALSE(cache.load<uint8_t>(other));
  other = key;
  other.inputs ^= 1;  // an input file changed: same file, header mismatch
  EXPECT_EQ(cache.path_of(other), cache.path_of(key));
  EXPECT_FALSE(cache.load<uint8_t>(other));
  other = key;
  other.frame = 124;
  EXPECT_FALSE(cache.load<uint8_t>(other));
  other = key;
  other.sequence = "/data/sequences/09";
  EXPECT_FALSE(cache.load<uint8_t>(other));
  EXPECT_FALSE(cache.load<uint16_t>(key));  // another dtype

  // The store under the new inputs replaces the stale entry.
  other = key;
  other.inputs ^= 1;
  cache.store(other, ramp<uint8_t>({1, 2}));
  EXPECT_FALSE(cache.load<uint8_t>(key));
  ASSERT_TRUE(cache.load<uint8_t>(other));
  EXPECT_EQ(cache.load<uint8_t>(other)->shape(), (Shape{1, 2}));
}

TEST(Cache, FileStampFollowsRewritesAndTouches) {
  const fs::path dir = test::temp_dir();
  const fs::path bin = dir / "000000.bin";
  write_file_atomic(bin, std::string(32, 'x').data(), 32);
  const auto stamp = [&] {
    Hasher h;
    hash_file_stamp(h, bin);
    return h.digest();
  };
  const uint64_t first = stamp();
  EXPECT_EQ(stamp(), first);
  const Cache cache(dir / "cache");
  CacheKey key = sample_key();
  key.inputs = first;
  cache.store(key, ramp<uint8_t>({2, 2}));

  // Same size, later mtime (touch).
  fs::last_write_time(bin, fs::last_write_time(bin) + std::chrono::seconds(3));
  const uint64_t touched = stamp();
  EXPECT_NE(touched, first);
  key.inputs = touched;
  EXPECT_FALSE(cache.load<uint8_t>(key));
  // Other size, mtime restored: still a change.
  const auto mtime = fs::last_write_time(bin);
  write_file_atomic(bin, std::string(48, 'y').data(), 48);
  fs::last_write_time(bin, mtime);
  EXPECT_NE(stamp(), touched);
  // A missing file has a stamp of its own.
  fs::remove(bin);
  EXPECT_NE(stamp(), first);
  EXPECT_NO_THROW(stamp());
}

TEST(Cache, CorruptOrTruncatedFilesAreMissesAndGetRewritten) {
  const Cache cache(test::temp_dir());
  const CacheKey key = sample_key();
  const Tensor<uint16_t> good = ramp<uint16_t>({10, 20});
  cache.store(key, good);
  const fs::path path = cache.path_of(key);
  const std::vector<char> bytes = read_file_bytes(path);

  std::vector<std::pair<std::string, std::vector<char>>> damaged;
  damaged.emplace_back("empty", std::vector<char>{});
  damaged.emplace_back("magic only", std::vector<char>(bytes.begin(), bytes.begin() + 8));
  damaged.emplace_back("cut in the key", std::vector<char>(bytes.begin(), bytes.begin() + 20));
  damaged.emplace_back("cut in the payload", std::vector<char>(bytes.begin(), bytes.end() - 7));
  damaged.emplace_back("one byte short", std::vector<char>(bytes.begin(), bytes.end() - 1));
  std::vector<char> longer = bytes;
  longer.push_back('z');
  damaged.emplace_back("trailing byte", longer);
  std::vector<char> flipped = bytes;
  flipped[bytes.size() - 5] ^= 0x10;
  damaged.emplace_back("payload bit flip", flipped);
  std::vector<char> magic = bytes;
  magic[3] = 'X';
  damaged.emplace_back("bad magic", magic);
  std::vector<char> huge_dim = bytes;
  // The first dimension follows magic, version, key length, key, dtype and rank.
  const size_t dim_offset = 8 + 4 + 4 + key.text().size() + 4 + 4;
  const int64_t huge = std::numeric_limits<int64_t>::max() / 2;
  std::memcpy(huge_dim.data() + dim_offset, &huge, sizeof huge);
  damaged.emplace_back("huge dimension", huge_dim);
  std::vector<char> negative_dim = bytes;
  const int64_t negative = -20;
  std::memcpy(negative_dim.data() + dim_offset, &negative, sizeof negative);
  damaged.emplace_back("negative dimension", negative_dim);
  damaged.emplace_back("garbage", std::vector<char>(4096, '\x5A'));

  for (const auto& [what, content] : damaged) {
    write_bytes(path, content);
    std::optional<Tensor<uint16_t>> loaded;
    EXPECT_NO_THROW(loaded = cache.load<uint16_t>(key)) << what;
    EXPECT_FALSE(loaded) << what;
    cache.store(key, good);  // rewritten over the damaged file
    loaded = cache.load<uint16_t>(key);
    ASSERT_TRUE(loaded) << what;
    EXPECT_EQ(loaded->values(), good.values()) << what;
  }
  // A directory where the file should be is a miss as well.
  fs::remove(path);
  fs::create_directories(path);
  EXPECT_FALSE(cache.load<uint16_t>(key));
}

TEST(Cache, WritesAreAtomicAndLeaveNoTemporaryFiles) {
  const fs::path dir = test::temp_dir();
  const Cache cache(dir / "nested" / "cache");  // created on first store
  CacheKey key = sample_key();
  for (int frame = 0; frame < 20; ++frame) {
    key.frame = frame;
    cache.store(key, ramp<uint8_t>({16, 16}));
    cache.store(key, ramp<uint8_t>({8, 8}));  // overwrite in place
  }
  size_t files = 0;
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    EXPECT_EQ(entry.path().filename().string().find(".tmp"), std::string::npos) << entry.path();
    files += entry.is_regular_file();
  }
  EXPECT_EQ(files, 20u);
  // A store that cannot write throws and leaves the previous entry intact.
  key.frame = 0;
  const fs::path blocker = dir / "blocked";
  write_file_atomic(blocker, "x", 1);
  const Cache unwritable(blocker / "cache");  // a file where a directory is needed
  EXPECT_THROW(unwritable.store(key, ramp<uint8_t>({2})), Error);
  EXPECT_EQ(cache.load<uint8_t>(key)->shape(), (Shape{8, 8}));
}

TEST(Cache, DefaultDirectory) {
  const fs::path dir = test::temp_dir();
  EXPECT_EQ(default_cache_dir(dir), dir / "pillarseg_cache");
  {
    const test::ScopedEnv xdg("XDG_CACHE_HOME", (dir / "xdg").c_str());
    // A data root that does not exist cannot hold the cache.
    EXPECT_EQ(default_cache_dir(dir / "missing"), dir / "xdg" / "pillarseg");
  }
  {
    const test::ScopedEnv xdg("XDG_CACHE_HOME", nullptr);
    const test::ScopedEnv home("HOME", (dir / "home").c_str());
    EXPECT_EQ(default_cache_dir(dir / "missing"), dir / "home" / ".cache" / "pillarseg");
    const test::ScopedEnv no_home("HOME", nullptr);
    EXPECT_THROW(default_cache_dir(dir / "missing"), Error);
  }
}
