// Confusion matrix, IoU and mIoU on hand-computed cases; the Markdown and JSON reports.
#include <gtest/gtest.h>

#include <cmath>

#include "core/error.hpp"
#include "engine/eval/metrics.hpp"

using namespace pillarseg;

TEST(Metrics, HandComputedIoU) {
  // truth:     1 1 2 0 | 5 5 5 2
  // predicted: 1 2 2 7 | 5 5 1 2
  Tensor<uint8_t> truth({2, 4}), pred({2, 4});
  const uint8_t t[] = {1, 1, 2, 0, 5, 5, 5, 2}, p[] = {1, 2, 2, 7, 5, 5, 1, 2};
  for (int i = 0; i < 8; ++i) truth[i] = t[i], pred[i] = p[i];
  SegmentationMetrics m;
  m.add(truth, pred);
  EXPECT_EQ(m.labelled_cells(), 7);  // the unlabeled cell is skipped
  // vehicle (1): TP 1, FN 1 (pred 2), FP 1 (truth 5 pred 1) -> 1/3
  EXPECT_NEAR(m.iou(1), 1.0 / 3.0, 1e-12);
  // person (2): TP 2, FP 1 -> 2/3
  EXPECT_NEAR(m.iou(2), 2.0 / 3.0, 1e-12);
  // road (5): TP 2, FN 1 -> 2/3
  EXPECT_NEAR(m.iou(5), 2.0 / 3.0, 1e-12);
  EXPECT_TRUE(std::isnan(m.iou(7)));  // predicted only where truth is unlabeled: empty union
  EXPECT_NEAR(m.miou(), (1.0 / 3 + 2.0 / 3 + 2.0 / 3) / 3, 1e-12);
  EXPECT_NEAR(m.accuracy(), 5.0 / 7.0, 1e-12);
}

TEST(Metrics, MaskAndAccumulationOverSplit) {
  Tensor<uint8_t> truth({1, 3}), pred({1, 3}), mask({1, 3});
  truth[0] = 3, truth[1] = 3, truth[2] = 4;
  pred[0] = 3, pred[1] = 4, pred[2] = 4;
  mask[0] = 1, mask[1] = 0, mask[2] = 1;
  SegmentationMetrics a, b;
  a.add(truth, pred, &mask);
  EXPECT_EQ(a.labelled_cells(), 2);
  EXPECT_NEAR(a.iou(3), 1.0, 1e-12);
  b.add(truth, pred);
  a.merge(b);
  // Accumulated over the split, not averaged per scan: two-wheel TP 2, FN 1 -> 2/3.
  EXPECT_NEAR(a.iou(3), 2.0 / 3.0, 1e-12);
  EXPECT_NEAR(a.iou(4), 2.0 / 3.0, 1e-12);
}

TEST(Metrics, ReportsAndBadInput) {
  Tensor<uint8_t> truth({2}), pred({2});
  truth[0] = 1, pred[0] = 1, truth[1] = 12, pred[1] = 1;
  SegmentationMetrics m;
  m.add(truth, pred);
  const ClassTable classes = ClassTable::defaults();
  const std::string md = m.markdown_table(classes, "Sparse Eval", "Pillar");
  EXPECT_NE(md.find("| Sparse Eval | Pillar | **25.0** | 50.0 | - |"), std::string::npos) << md;
  EXPECT_NE(md.find("terrain"), std::string::npos);
  const std::string js = m.json(classes, "Sparse Eval", "Pillar");
  EXPECT_NE(js.find("\"miou\": 0.250000"), std::string::npos) << js;
  EXPECT_NE(js.find("\"person\": null"), std::string::npos) << js;
  Tensor<uint8_t> bad({2});
  bad[0] = 0, bad[1] = 1;  // prediction 0 is not a class
  EXPECT_THROW(m.add(truth, bad), Error);
  Tensor<uint8_t> other({3});
  EXPECT_THROW(m.add(truth, other), Error);
}
