#include "engine/eval/metrics.hpp"

#include <fmt/format.h>

#include <cmath>
#include <limits>
#include <utility>

#include "host/confusion.hpp"

namespace pillarseg {

SegmentationMetrics::SegmentationMetrics() : confusion_({kNumClasses, kNumClasses}) {}

SegmentationMetrics::SegmentationMetrics(Tensor<int64_t> confusion) : confusion_(std::move(confusion)) {
  PS_CHECK(confusion_.shape() == (Shape{kNumClasses, kNumClasses}), "a confusion matrix must be ({0}, {0}), got {1}",
           kNumClasses, shape_str(confusion_.shape()));
}

void SegmentationMetrics::add(const Tensor<uint8_t>& truth, const Tensor<uint8_t>& predicted,
                              const Tensor<uint8_t>* mask) {
  host::confusion_accumulate(truth, predicted, mask, confusion_);
}

void SegmentationMetrics::merge(const SegmentationMetrics& other) {
  for (int64_t i = 0; i < confusion_.numel(); ++i) confusion_[i] += other.confusion_[i];
}

double SegmentationMetrics::iou(int class_id) const {
  const int k = class_id - 1;
  int64_t tp = confusion_(k, k), fp = 0, fn = 0;
  for (int j = 0; j < kNumClasses; ++j) {
    if (j == k) continue;
    fn += confusion_(k, j);
    fp += confusion_(j, k);
  }
  const int64_t union_ = tp + fp + fn;
  if (union_ == 0) return std::numeric_limits<double>::quiet_NaN();
  return static_cast<double>(tp) / static_cast<double>(union_);
}

double SegmentationMetrics::miou() const {
  double sum = 0;
  int n = 0;
  for (int c = 1; c <= kNumClasses; ++c) {
    const double v = iou(c);
    if (!std::isnan(v)) sum += v, ++n;
  }
  return n ? sum / n : std::numeric_limits<double>::quiet_NaN();
}

int64_t SegmentationMetrics::labelled_cells() const {
  int64_t n = 0;
  for (int64_t i = 0; i < confusion_.numel(); ++i) n += confusion_[i];
  return n;
}

double SegmentationMetrics::accuracy() const {
  int64_t correct = 0;
  for (int k = 0; k < kNumClasses; ++k) correct += confusion_(k, k);
  const int64_t n = labelled_cells();
  return n ? static_cast<double>(correct) / static_cast<double>(n) : std::numeric_limits<double>::quiet_NaN();
}

namespace {
std::string percent(double v) { return std::isnan(v) ? "-" : fmt::format("{:.1f}", 100.0 * v); }
std::string json_number(double v) { return std::isnan(v) ? "null" : fmt::format("{:.6f}", v); }
std::string json_string(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') out += '\\';
    if (static_cast<unsigned char>(c) < 0x20) {
      out += fmt::format("\\u{:04x}", static_cast<int>(c));
      continue;
    }
    out += c;
  }
  return out + "\"";
}
}  // namespace

std::string SegmentationMetrics::markdown_table(const ClassTable& classes, const std::string& mode,
                                                const std::string& method) const {
  std::string header = "| Mode | Method | mIoU [%] |", rule = "|---|---|---:|";
  std::string row = fmt::format("| {} | {} | **{}** |", mode, method, percent(miou()));
  for (int c = 1; c <= kNumClasses; ++c) {
    header += fmt::format(" {} |", classes.name(c));
    rule += "---:|";
    row += fmt::format(" {} |", percent(iou(c)));
  }
  return header + "\n" + rule + "\n" + row + "\n";
}

std::string SegmentationMetrics::json(const ClassTable& classes, const std::string& mode,
                                      const std::string& method) const {
  std::string s = "{\n";
  s += fmt::format("  \"mode\": {},\n  \"method\": {},\n", json_string(mode), json_string(method));
  s += fmt::format("  \"miou\": {},\n  \"accuracy\": {},\n  \"labelled_cells\": {},\n", json_number(miou()),
                   json_number(accuracy()), labelled_cells());
  s += "  \"iou\": {";
  for (int c = 1; c <= kNumClasses; ++c)
    s += fmt::format("{}{}: {}", c > 1 ? ", " : "", json_string(classes.name(c)), json_number(iou(c)));
  s += "},\n  \"confusion\": [";
  for (int k = 0; k < kNumClasses; ++k) {
    s += k ? ",\n    [" : "\n    [";
    for (int j = 0; j < kNumClasses; ++j) s += fmt::format("{}{}", j ? ", " : "", confusion_(k, j));
    s += "]";
  }
  s += "\n  ]\n}\n";
  return s;
}

}  // namespace pillarseg
