// Segmentation metrics (DESIGN.md section 3): a confusion matrix accumulated over a whole
// split, IoU_k = TP / (TP + FP + FN), mIoU over the classes with a non-empty union; reports
// as a Markdown table in the layout of the paper's Table I, and as JSON.
#pragma once

#include <array>
#include <cstdint>
#include <string>

#include "core/classes.hpp"
#include "core/tensor.hpp"

namespace pillarseg {

class SegmentationMetrics {
 public:
  SegmentationMetrics();
  // From a (12, 12) confusion matrix (e.g. the sum of several processes').
  explicit SegmentationMetrics(Tensor<int64_t> confusion);
  // truth, predicted: (B, H, W) or (H, W); mask (observability) or nullptr.
  void add(const Tensor<uint8_t>& truth, const Tensor<uint8_t>& predicted, const Tensor<uint8_t>* mask = nullptr);
  void merge(const SegmentationMetrics& other);

  const Tensor<int64_t>& confusion() const { return confusion_; }
  // IoU of class id 1..12 in [0, 1]; NaN when the class has an empty union.
  double iou(int class_id) const;
  double miou() const;  // mean over classes with a non-empty union; NaN if none
  int64_t labelled_cells() const;
  double accuracy() const;

  // | Mode | Method | mIoU | vehicle | ... | terrain |, values in percent with one decimal.
  std::string markdown_table(const ClassTable& classes, const std::string& mode, const std::string& method) const;
  std::string json(const ClassTable& classes, const std::string& mode, const std::string& method) const;

 private:
  Tensor<int64_t> confusion_;  // (12, 12): row true class, column predicted
};

}  // namespace pillarseg
