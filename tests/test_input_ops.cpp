// The small host ops of the input pipeline (engine/pipeline/), on hand-computed cases: point
// padding, batch cells, the 2D occupancy input and the masking of unobserved cells.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <string>

#include "core/error.hpp"
#include "core/tensor.hpp"
#include "host/mask_unobserved.hpp"
#include "host/observability_input.hpp"
#include "host/pad_points.hpp"
#include "host/scatter.hpp"

using namespace pillarseg;

namespace {

template <class T>
Tensor<T> tensor(const Shape& shape, std::initializer_list<T> values) {
  Tensor<T> t(shape);
  std::copy(values.begin(), values.end(), t.begin());
  return t;
}

std::string error_of(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  return "(no error)";
}

}  // namespace

TEST(PadPoints, RowsPastTheScanBecomeNan) {
  Tensor<float> points({3, 4});
  for (int64_t i = 0; i < points.numel(); ++i) points[i] = static_cast<float>(i);
  host::pad_points(1, points);
  for (int64_t i = 0; i < 4; ++i) EXPECT_EQ(points[i], static_cast<float>(i));
  for (int64_t i = 4; i < 12; ++i) EXPECT_TRUE(std::isnan(points[i])) << i;
  host::pad_points(3, points);  // a full buffer: nothing changes
  EXPECT_EQ(points[0], 0.0f);
  host::pad_points(0, points);
  EXPECT_TRUE(std::isnan(points[0]));
  EXPECT_NE(error_of([&] { host::pad_points(4, points); }).find("4 points do not fit the buffer of 3 rows"),
            std::string::npos);
  Tensor<float> wrong({3, 3});
  EXPECT_NE(error_of([&] { host::pad_points(0, wrong); }).find("(capacity, 4)"), std::string::npos);
}

TEST(BatchCells, SampleIndexAndInertRows) {
  const Tensor<int32_t> cell = tensor<int32_t>({3, 2}, {4, 7, -1, -1, 0, 2});
  Tensor<int32_t> cells({3, 3});
  host::batch_cells(cell, 5, cells);
  const Tensor<int32_t> expected = tensor<int32_t>({3, 3}, {5, 4, 7, -1, -1, -1, 5, 0, 2});
  EXPECT_EQ(std::vector<int32_t>(cells.begin(), cells.end()),
            std::vector<int32_t>(expected.begin(), expected.end()));
  Tensor<int32_t> short_cells({2, 3});
  EXPECT_NE(error_of([&] { host::batch_cells(cell, 0, short_cells); }).find("cells (R, 3)"), std::string::npos);
}

TEST(ObservabilityInput, LogOfOnePlusTheRays) {
  const Tensor<uint32_t> t = tensor<uint32_t>({1, 3}, {0, 1, 6});
  const Tensor<uint32_t> d = tensor<uint32_t>({1, 3}, {0, 2, 1});
  Tensor<float> out({1, 1, 3});
  host::observability_input(t, d, out);
  EXPECT_EQ(out[0], 0.0f);
  EXPECT_EQ(out[1], static_cast<float>(std::log(4.0)));
  EXPECT_EQ(out[2], static_cast<float>(std::log(8.0)));
  Tensor<float> small({2});
  EXPECT_NE(error_of([&] { host::observability_input(t, d, small); }).find("H * W = 3"), std::string::npos);
}

TEST(MaskUnobserved, ClearsLabelsAndEveryProbabilityPlane) {
  const Tensor<uint32_t> t = tensor<uint32_t>({1, 3}, {0, 0, 2});
  const Tensor<uint32_t> d = tensor<uint32_t>({1, 3}, {0, 1, 0});
  Tensor<uint8_t> labels = tensor<uint8_t>({1, 3}, {3, 4, 5});
  Tensor<float> probs = tensor<float>({2, 1, 3}, {0.5f, 0.25f, 0.75f, 0.5f, 0.75f, 0.25f});
  host::mask_unobserved(t, d, labels, &probs);
  EXPECT_EQ(std::vector<uint8_t>(labels.begin(), labels.end()), (std::vector<uint8_t>{0, 4, 5}));
  EXPECT_EQ(std::vector<float>(probs.begin(), probs.end()),
            (std::vector<float>{0.0f, 0.25f, 0.75f, 0.0f, 0.75f, 0.25f}));
  Tensor<float> ragged({4});
  EXPECT_NE(error_of([&] { host::mask_unobserved(t, d, labels, &ragged); }).find("not whole class planes"),
            std::string::npos);
}
