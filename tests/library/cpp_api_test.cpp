// The C++ API (include/pillarseg/pillarseg.hpp), included alone as a user includes it: RAII, move
// semantics, failures as pillarseg::Error with the C API's message.
#include <gtest/gtest.h>

#include <cmath>
#include <cstddef>
#include <cstdio>
#include <string>
#include <utility>
#include <vector>

#include "pillarseg/pillarseg.hpp"
#include "tests/library/fixtures.hpp"

TEST(CppApi, SegmentsLikeTheCApi) {
  pillarseg::Segmenter segmenter(pillarseg_test::tiny_checkpoint());
  EXPECT_EQ(segmenter.width(), 64);
  EXPECT_EQ(segmenter.height(), 32);
  EXPECT_EQ(segmenter.cells(), 2048u);
  EXPECT_EQ(segmenter.device(), "cpu");
  const std::vector<float> scan = pillarseg_test::tiny_scan(2000, 21);
  const std::vector<std::uint8_t> labels = segmenter.segment(scan);
  std::vector<std::uint8_t> c_labels(segmenter.cells());
  char error[256];
  ASSERT_EQ(pillarseg_segment(segmenter.handle(), scan.data(), scan.size() / 4, c_labels.data(), nullptr, error,
                              sizeof error),
            0)
      << error;
  EXPECT_EQ(labels, c_labels);
  std::vector<float> probabilities(12 * segmenter.cells());
  segmenter.segment(scan.data(), scan.size() / 4, c_labels.data(), probabilities.data());
  EXPECT_EQ(labels, c_labels);
  EXPECT_EQ(pillarseg::class_name(2), "person");
  EXPECT_EQ(pillarseg::class_name(99), "");
}

TEST(CppApi, MovesAndErrors) {
  pillarseg::Segmenter a(pillarseg_test::tiny_checkpoint());
  pillarseg::Segmenter b = std::move(a);
  EXPECT_EQ(a.handle(), nullptr);  // NOLINT(bugprone-use-after-move): moved-from is empty
  EXPECT_NE(b.handle(), nullptr);
  a = std::move(b);
  EXPECT_NE(a.handle(), nullptr);
  try {
    pillarseg::Segmenter missing("/no/such/model.safetensors");
    FAIL() << "a missing file must throw";
  } catch (const pillarseg::Error& e) {
    EXPECT_NE(std::string(e.what()).find("/no/such/model.safetensors: no such file"), std::string::npos) << e.what();
  }
  try {
    a.segment(std::vector<float>(7));
    FAIL() << "7 floats are not whole points";
  } catch (const pillarseg::Error& e) {
    EXPECT_NE(std::string(e.what()).find("7 floats are not whole points"), std::string::npos) << e.what();
  }
  pillarseg::Options options;
  options.device = "emu";
  pillarseg::Segmenter emu(pillarseg_test::tiny_checkpoint(), options);
  EXPECT_EQ(emu.device().rfind("emu:0 (", 0), 0u) << emu.device();
}

TEST(CppApi, ReadPointsAndTheInputMapping) {
  const std::vector<float> scan = pillarseg_test::tiny_scan(500, 4);
  const std::string file = std::string(PILLARSEG_BINARY_DIR) + "/tests/cpp_api_scan.bin";
  {
    std::FILE* f = std::fopen(file.c_str(), "wb");
    ASSERT_NE(f, nullptr);
    std::fwrite(scan.data(), sizeof(float), scan.size(), f);
    std::fclose(f);
  }
  std::vector<float> finite;
  for (size_t i = 0; i < scan.size(); i += 4)
    if (std::isfinite(scan[i]) && std::isfinite(scan[i + 1]) && std::isfinite(scan[i + 2]) && std::isfinite(scan[i + 3]))
      finite.insert(finite.end(), scan.begin() + static_cast<std::ptrdiff_t>(i),
                    scan.begin() + static_cast<std::ptrdiff_t>(i + 4));
  EXPECT_EQ(pillarseg::read_points(file), finite);
  EXPECT_EQ(pillarseg::read_points(file, "kitti"), finite);
  try {
    pillarseg::read_points(file, "ply");
    ADD_FAILURE() << "a KITTI file read as PLY";
  } catch (const pillarseg::Error& e) {
    EXPECT_NE(std::string(e.what()).find("not a PLY file"), std::string::npos) << e.what();
  }
  std::remove(file.c_str());
  // No reflectance from the sensor: the same map as reflectance 0 given by hand.
  pillarseg::Options options;
  options.reflectance_none = true;
  pillarseg::Segmenter none(pillarseg_test::tiny_checkpoint(), options);
  pillarseg::Segmenter plain(pillarseg_test::tiny_checkpoint());
  std::vector<float> zeroed = finite;
  for (size_t i = 3; i < zeroed.size(); i += 4) zeroed[i] = 0;
  EXPECT_EQ(none.segment(finite), plain.segment(zeroed));
}
