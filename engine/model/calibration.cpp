#include "engine/model/calibration.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

#include "core/error.hpp"
#include "engine/model/parameters.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "host/winograd_f2_stats.hpp"

namespace pillarseg {

float abs_percentile(std::span<const float> values, double percentile) {
  PS_CHECK(percentile > 0 && percentile <= 100, "calibration: the percentile must be in (0, 100], got {}",
           percentile);
  std::vector<float> magnitudes;
  magnitudes.reserve(values.size());
  for (const float v : values)
    if (!std::isnan(v)) magnitudes.push_back(std::abs(v));
  if (magnitudes.empty()) return 0.0f;
  // Nearest rank: the smallest value with at least p% of the values at or below it.
  const auto n = static_cast<double>(magnitudes.size());
  const auto rank = static_cast<size_t>(std::max(1.0, std::ceil(percentile / 100.0 * n)));
  const auto nth = magnitudes.begin() + static_cast<std::ptrdiff_t>(rank - 1);
  std::nth_element(magnitudes.begin(), nth, magnitudes.end());
  return *nth;
}

InputScaleCalibrator::InputScaleCalibrator(double percentile) : percentile_(percentile) {
  PS_CHECK(percentile > 0 && percentile <= 100, "calibration: the percentile must be in (0, 100], got {}",
           percentile);
}

void InputScaleCalibrator::add(const std::string& key, std::span<const float> values) {
  const float p = abs_percentile(values, percentile_);
  PS_CHECK(std::isfinite(p), "calibration: the input of {} has an infinite value in its top {}%", key,
           100 - percentile_);
  float& largest = largest_[key];
  largest = std::max(largest, p);
  bool& negative = negative_[key];
  negative = negative || std::any_of(values.begin(), values.end(), [](float v) { return v < 0; });
  ++count_[key];
}

void InputScaleCalibrator::add_winograd(const std::string& key, std::span<const float> values, const Shape& shape) {
  PS_CHECK(shape.size() == 4 && static_cast<size_t>(shape_numel(shape)) == values.size(),
           "calibration: the input of {} is not (B, C, H, W) with {} values, got {}", key, values.size(),
           shape_str(shape));
  add(key, values);
  const std::array<float, 16> p = host::winograd_f2_input_percentiles(values.data(), shape, percentile_);
  std::array<float, 16>& largest = largest_winograd_[key];
  for (size_t i = 0; i < 16; ++i) {
    PS_CHECK(std::isfinite(p[i]), "calibration: the Winograd-domain input of {} has an infinite value at position {}",
             key, i);
    largest[i] = std::max(largest[i], p[i]);
  }
}

std::map<std::string, Int8Input> InputScaleCalibrator::inputs() const {
  std::map<std::string, Int8Input> out;
  for (const auto& [key, largest] : largest_) {
    const bool non_negative = !negative_.at(key);
    Int8Input& input = out[key];
    input = Int8Input{.scale = std::max(largest / (non_negative ? 255.0f : 127.0f), 1e-8f),
                      .non_negative = non_negative};
    const auto winograd = largest_winograd_.find(key);
    if (winograd == largest_winograd_.end()) continue;
    for (size_t p = 0; p < 16; ++p) input.winograd[p] = std::max(winograd->second[p] / 127.0f, 1e-8f);
  }
  return out;
}

int64_t InputScaleCalibrator::forwards(const std::string& key) const {
  const auto it = count_.find(key);
  return it == count_.end() ? 0 : it->second;
}

std::map<std::string, std::vector<float>> int8_weight_scales(const ParameterSet& ps,
                                                             const std::vector<std::string>& keys) {
  std::map<std::string, std::vector<float>> out;
  for (const std::string& key : keys) {
    const int w_index = ps.find(key + ".weight");
    PS_CHECK(w_index >= 0, "calibration: no weight {}.weight", key);
    const Tensor<float> w = ps.download(w_index);
    PS_CHECK(w.rank() == 4, "calibration: {}.weight is not a convolution's", key);
    // The DoubleConv's BatchNorm after its convolution .0 / .3 is .1 / .4.
    std::string bn;
    for (const auto& [conv, norm] : {std::pair{".double_conv.0", ".double_conv.1"}, {".double_conv.3", ".double_conv.4"}})
      if (key.ends_with(conv)) bn = key.substr(0, key.size() - std::string(conv).size()) + norm;
    const bool transposed = key.ends_with(".up");
    const int64_t out_channels = transposed ? w.dim(1) : w.dim(0);
    std::vector<float> scale(static_cast<size_t>(out_channels), 1.0f);
    if (!bn.empty()) {
      const Tensor<float> gamma = ps.download(ps.find(bn + ".weight")), var = ps.download(ps.find(bn + ".running_var"));
      for (int64_t o = 0; o < out_channels; ++o)
        scale[static_cast<size_t>(o)] = gamma.data()[o] / std::sqrt(var.data()[o] + 1e-5f);
    }
    std::vector<float>& largest = out[key];
    largest.assign(static_cast<size_t>(out_channels), 0.0f);
    for (int64_t i = 0; i < w.numel(); ++i) {
      const int64_t o = transposed ? (i / 4) % out_channels : i / (w.numel() / out_channels);
      float& l = largest[static_cast<size_t>(o)];
      l = std::max(l, std::abs(w.data()[i] * scale[static_cast<size_t>(o)]));
    }
    for (float& l : largest) l /= 127.0f;
  }
  return out;
}

CalibrationScope::CalibrationScope(PillarSegNet& net, InputScaleCalibrator& calibrator) : net_(net) {
  Backend& backend = net.backend();
  net.set_conv_input_observer([this, &backend, &calibrator](const std::string& key, const TensorRef& x, bool winograd) {
    PS_CHECK(x.dtype == DType::F32, "calibration: the forward is not FP32 (an input of {} is {})", key,
             dtype_name(x.dtype));
    host_.resize(static_cast<size_t>(x.numel()));
    backend.download(host_.data(), x.data, host_.size() * sizeof(float));
    if (winograd) {
      calibrator.add_winograd(key, host_, x.shape);
    } else {
      calibrator.add(key, host_);
    }
  });
}

CalibrationScope::~CalibrationScope() { net_.set_conv_input_observer(nullptr); }

std::string input_scale_name(const std::string& key) { return kQuantizationPrefix + key + ".input_scale"; }
std::string weight_scale_name(const std::string& key) { return kQuantizationPrefix + key + ".weight_scale"; }
std::string winograd_input_scale_name(const std::string& key) {
  return kQuantizationPrefix + key + ".winograd_input_scale";
}
std::string input_non_negative_name(const std::string& key) {
  return kQuantizationPrefix + key + ".input_non_negative";
}

}  // namespace pillarseg
