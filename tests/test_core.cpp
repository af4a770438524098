// Core utilities: RNG determinism and distributions, the grid, the class table, atomic files.
#include <gtest/gtest.h>

#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <fstream>

#include "core/classes.hpp"
#include "core/grid.hpp"
#include "core/io.hpp"
#include "core/rng.hpp"
#include "engine/data/class_table_yaml.hpp"
#include "engine/util/image.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;

TEST(Rng, SameSeedSameStreamAndStateRoundTrip) {
  Rng a(42), b(42), c(43);
  for (int i = 0; i < 100; ++i) {
    const uint64_t va = a.next_u64();
    EXPECT_EQ(va, b.next_u64());
    if (i == 0) {
      EXPECT_NE(va, c.next_u64());
    }
  }
  Rng d(7);
  d.next_u64();
  Rng e;
  e.set_state(d.state());
  EXPECT_EQ(d.next_u64(), e.next_u64());
  EXPECT_NE(Rng::derive(1, 2, 3).next_u64(), Rng::derive(1, 3, 2).next_u64());
}

TEST(Rng, DistributionMoments) {
  Rng r(1);
  const int n = 200000;
  double su = 0, sn = 0, sn2 = 0;
  int64_t hist[10] = {};
  for (int i = 0; i < n; ++i) {
    const double u = r.uniform();
    ASSERT_GE(u, 0.0);
    ASSERT_LT(u, 1.0);
    su += u;
    const double z = r.normal();
    sn += z, sn2 += z * z;
    hist[r.uniform_int(10)]++;
  }
  EXPECT_NEAR(su / n, 0.5, 0.005);
  EXPECT_NEAR(sn / n, 0.0, 0.01);
  EXPECT_NEAR(sn2 / n, 1.0, 0.02);
  for (int64_t h : hist) EXPECT_NEAR(static_cast<double>(h) / n, 0.1, 0.005);
}

TEST(Grid, DefaultsAndCellIndices) {
  GridSpec g;
  EXPECT_EQ(g.width(), 1000);
  EXPECT_EQ(g.height(), 500);
  EXPECT_EQ(g.layers(), 20);
  EXPECT_EQ(g.ix(-50.0), 0);
  EXPECT_EQ(g.ix(-49.95), 0);
  EXPECT_EQ(g.ix(0.0), 500);
  EXPECT_EQ(g.ix(-0.05), 499);
  EXPECT_EQ(g.iy(24.99), 499);
  EXPECT_TRUE(g.contains(49.99, 24.99, 1.49));
  EXPECT_FALSE(g.contains(50.0, 0, 0));
  EXPECT_FALSE(g.contains(0, -25.01, 0));
  EXPECT_FALSE(g.contains(0, 0, 1.5));
  EXPECT_TRUE(g.contains(0, 0, -2.5));
  EXPECT_EQ(g.iz(-2.5), 0);
  EXPECT_EQ(g.iz(1.49), 19);
}

TEST(ClassTable, DefaultMapping) {
  const ClassTable t = ClassTable::defaults();
  EXPECT_EQ(t.class_of(10), 1);
  EXPECT_EQ(t.class_of(252), 1);
  EXPECT_EQ(t.class_of(30), 2);
  EXPECT_EQ(t.class_of(11), 3);
  EXPECT_EQ(t.class_of(253), 4);
  EXPECT_EQ(t.class_of(60), 5);
  EXPECT_EQ(t.class_of(48), 6);
  EXPECT_EQ(t.class_of(49), 7);
  EXPECT_EQ(t.class_of(50), 8);
  EXPECT_EQ(t.class_of(81), 9);
  EXPECT_EQ(t.class_of(70), 10);
  EXPECT_EQ(t.class_of(71), 11);
  EXPECT_EQ(t.class_of(72), 12);
  EXPECT_EQ(t.class_of(52), 0);
  EXPECT_EQ(t.class_of(1234), 0);                 // not listed
  EXPECT_EQ(t.class_of((77u << 16) | 10u), 1);    // instance bits ignored
  EXPECT_TRUE(t.is_moving((5u << 16) | 257u));
  EXPECT_FALSE(t.is_moving(10));
  EXPECT_EQ(t.gt_weight(1), 5);
  EXPECT_EQ(t.gt_weight(5), 1);
  EXPECT_EQ(t.gt_weight(0), 0);
  EXPECT_EQ(t.color(5), (Rgb{255, 0, 255}));
}

TEST(ClassTable, YamlOverrideMovesRawIdsAndChangesFingerprint) {
  const auto dir = test::temp_dir();
  {
    std::ofstream f(dir / "classes.yaml");
    f << "classes:\n  - {id: 9, raw: [51, 80, 81, 52]}\n  - {id: 2, gt_weight: 7, color: [1, 2, 3]}\n";
  }
  const ClassTable t = load_class_table((dir / "classes.yaml").string());
  EXPECT_EQ(t.class_of(52), 9);
  EXPECT_EQ(t.gt_weight(2), 7);
  EXPECT_EQ(t.color(2), (Rgb{1, 2, 3}));
  EXPECT_NE(t.fingerprint(), ClassTable::defaults().fingerprint());
  {
    std::ofstream f(dir / "bad.yaml");
    f << "classes:\n  - {id: 40}\n";
  }
  try {
    load_class_table((dir / "bad.yaml").string());
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("bad.yaml"), std::string::npos);
  }
}

TEST(Io, AtomicWriteLeavesNoFileOnFailure) {
  const auto dir = test::temp_dir();
  const auto target = dir / "out.bin";
  EXPECT_THROW(write_file_atomic(target, [](std::ostream&) { throw Error("boom"); }), Error);
  EXPECT_FALSE(std::filesystem::exists(target));
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(dir), {}), 0);
  const char data[] = "abc";
  write_file_atomic(target, data, 3);
  EXPECT_EQ(read_file_text(target), "abc");
  EXPECT_THROW(read_file_bytes(dir / "missing"), Error);
}

TEST(Io, AtomicWriteOfLargeFilesAndDeviceErrors) {
  const auto dir = test::temp_dir();
  // Larger than the write buffer, in pieces of every size: the bytes arrive in order.
  std::string expected;
  for (int i = 0; i < 3'000'000; ++i) expected.push_back(static_cast<char>(i * 7 + i / 1000));
  write_file_atomic(dir / "big.bin", [&](std::ostream& out) {
    size_t at = 0, piece = 1;
    while (at < expected.size()) {
      const size_t n = std::min(piece, expected.size() - at);
      out.write(expected.data() + at, static_cast<std::streamsize>(n));
      at += n;
      piece = piece * 3 + 1;
    }
  }, Durability::kPowerLoss);
  EXPECT_EQ(read_file_text(dir / "big.bin"), expected);
  // A directory where the file should go: the error names it, nothing is left behind.
  std::filesystem::create_directories(dir / "taken");
  try {
    write_file_atomic(dir / "taken", "x", 1);
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("taken"), std::string::npos) << e.what();
  }
  for (const auto& entry : std::filesystem::directory_iterator(dir))
    EXPECT_EQ(entry.path().filename().string().find(".tmp-"), std::string::npos) << entry.path();
}

// What a killed writer leaves: NAME.tmp-HOST-PID-N of a process that is gone is removed; a live
// process's, another host's and other files stay.
TEST(Io, RemovesOnlyDeadWritersTemporaries) {
  const auto dir = test::temp_dir();
  char name[256] = {};
  ASSERT_EQ(::gethostname(name, sizeof name - 1), 0);
  std::string host(name);
  for (char& c : host)
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '.' && c != '_') c = '_';
  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0) ::_exit(0);
  ASSERT_EQ(::waitpid(child, nullptr, 0), child);  // `child` names no process now
  const auto touch = [&](const std::string& file) {
    std::filesystem::create_directories((dir / file).parent_path());
    std::ofstream(dir / file) << "x";
  };
  const std::string dead = fmt::format("a.psc.tmp-{}-{}-0", host, child);
  const std::string live = fmt::format("b.psc.tmp-{}-{}-3", host, ::getpid());
  const std::string other_host = fmt::format("c.psc.tmp-{}x-{}-0", host, child);
  touch(dead), touch(live), touch(other_host), touch("d.psc"), touch("sub/" + dead);
  EXPECT_EQ(remove_stale_temporaries(dir, /*recursive=*/false), 1u);
  EXPECT_FALSE(std::filesystem::exists(dir / dead));
  EXPECT_TRUE(std::filesystem::exists(dir / live));
  EXPECT_TRUE(std::filesystem::exists(dir / other_host));
  EXPECT_TRUE(std::filesystem::exists(dir / "d.psc"));
  EXPECT_TRUE(std::filesystem::exists(dir / "sub" / dead));
  EXPECT_EQ(remove_stale_temporaries(dir, /*recursive=*/true), 1u);
  EXPECT_FALSE(std::filesystem::exists(dir / "sub" / dead));
  EXPECT_EQ(remove_stale_temporaries(dir / "missing", true), 0u);
}

TEST(Image, PngRoundTrip) {
  const auto dir = test::temp_dir();
  ImageRgb img(5, 3);
  for (int y = 0; y < 3; ++y)
    for (int x = 0; x < 5; ++x) {
      img.at(x, y)[0] = static_cast<uint8_t>(x * 40);
      img.at(x, y)[1] = static_cast<uint8_t>(y * 80);
      img.at(x, y)[2] = 7;
    }
  write_png_rgb(dir / "a.png", img);
  const ImageRgb back = read_png_rgb(dir / "a.png");
  EXPECT_EQ(back.width, 5);
  EXPECT_EQ(back.height, 3);
  EXPECT_EQ(back.pixels, img.pixels);
}

TEST(Tensor, OwningAndViewSemantics) {
  TensorF a({2, 3}, 1.5f);
  EXPECT_EQ(a.numel(), 6);
  EXPECT_EQ(a(1, 2), 1.5f);
  a(1, 2) = 4.0f;
  EXPECT_EQ(a[5], 4.0f);
  const TensorF copy = a;  // deep copy
  a[0] = 9.0f;
  EXPECT_EQ(copy[0], 1.5f);

  std::vector<float> memory(6, -1.0f);
  TensorF v = TensorF::view(memory.data(), {3, 2});
  EXPECT_TRUE(v.is_view());
  v.resize({6});  // same element count: zero-filled in place
  EXPECT_EQ(memory[3], 0.0f);
  EXPECT_THROW(v.resize({7}), Error);
  v = a;  // copies the elements into the view's memory
  EXPECT_EQ(v.data(), memory.data());
  EXPECT_EQ(memory[0], 9.0f);
  EXPECT_EQ(v.shape(), (Shape{2, 3}));
  EXPECT_THROW(v = TensorF({5}), Error);
  TensorF owned = v;  // copying a view gives an owning tensor
  EXPECT_FALSE(owned.is_view());
  owned[0] = 2.0f;
  EXPECT_EQ(memory[0], 9.0f);
  TensorF moved = std::move(a);
  EXPECT_EQ(moved.numel(), 6);
  EXPECT_EQ(a.numel(), 0);
}
