// The C++ API (include/pillarseg/pillarseg.hpp), included alone as a user includes it: RAII, move
// semantics, failures as pillarseg::Error with the C API's message.
#include <gtest/gtest.h>

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
