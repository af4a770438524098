// INT8 calibration (DESIGN.md section 10): the per-tensor scale of every U-Net convolution's
// input, from FP32 evaluation forwards over a few scans, and where the scales live in a
// checkpoint.
//
// The rule: a convolution's input scale is the largest, over the calibration scans, of the
// 99.999th percentile of |x| over the input's values, divided by 127 (so that q = x / scale fills
// [-127, 127]). A percentile rather than the maximum: one outlier among tens of millions of
// values (a pillar with an extreme reflectance or height, a ReLU output far in the tail) would
// otherwise set a scale that leaves most values a handful of levels; the 99.999th keeps the range
// of all but the top 0.001%, which saturate at +-127. Measured on the real scan with the demo's
// model calibrated on simulated scans (docs/benchmarks.md), arg-max agreement with FP32 on the
// cells with points: maximum 98.56%, 99.999th 98.97%, 99.99th 98.01%, 99.9th 94.10%: the
// U-Net's inputs have tails that matter, and clipping them costs more than coarser levels. (The
// entropy (KL) rule of TensorRT clips harder still.)
//
// In a checkpoint: quantization.<key>.input_scale (1) and quantization.<key>.weight_scale (O, the
// per-output-channel scales max |w'| / 127 of the weights with the BatchNorm folded in, for
// inspection: the backends derive them again from the weights), key the convolution's parameter
// prefix ("segmentation_head.down1.maxpool_conv.1.double_conv.0"). Loaders that do not know them
// skip them (engine/train/checkpoint.cpp), so a calibrated file loads as FP32 anywhere.
#pragma once

#include <cstdint>
#include <map>
#include <span>
#include <string>
#include <vector>

namespace pillarseg {

inline constexpr double kCalibrationPercentile = 99.999;

// The percentile (0 < p <= 100) of |v| over the values (nearest rank; 100: the maximum); NaN
// values are skipped; 0 for no finite values.
float abs_percentile(std::span<const float> values, double percentile);

// Collects the inputs of each convolution over forwards and gives their scales.
class InputScaleCalibrator {
 public:
  explicit InputScaleCalibrator(double percentile = kCalibrationPercentile);
  // One forward's input of the convolution `key`, on the host.
  void add(const std::string& key, std::span<const float> values);
  // key -> the largest percentile seen / 127 (at least 1e-8, so that an all-zero input still has
  // a valid scale).
  std::map<std::string, float> scales() const;
  int64_t forwards(const std::string& key) const;
  double percentile() const { return percentile_; }

 private:
  double percentile_;
  std::map<std::string, float> largest_;
  std::map<std::string, int64_t> count_;
};

class ParameterSet;
class PillarSegNet;

// While alive, every evaluation forward of `net` (in FP32) adds the input of each of its U-Net
// convolutions to `calibrator`, downloaded from the backend (the forwards run node by node).
class CalibrationScope {
 public:
  CalibrationScope(PillarSegNet& net, InputScaleCalibrator& calibrator);
  ~CalibrationScope();
  CalibrationScope(const CalibrationScope&) = delete;
  CalibrationScope& operator=(const CalibrationScope&) = delete;

 private:
  PillarSegNet& net_;
  std::vector<float> host_;
};

// The per-output-channel weight scales, max |w'| / 127, of the convolutions `keys` (their
// weights' names without ".weight"): w' the weights with their eval BatchNorm folded in as the
// backends prepare them (the BatchNorm that follows a DoubleConv's convolution "....double_conv.0"
// / ".3" is ".1" / ".4"; the transposed convolutions have none), one scale per output channel
// (a transposed weight (I, O, 2, 2): over I x 2 x 2). For the checkpoint's record of them.
std::map<std::string, std::vector<float>> int8_weight_scales(const ParameterSet& ps,
                                                             const std::vector<std::string>& keys);

// The checkpoint names of a convolution's scales.
std::string input_scale_name(const std::string& key);
std::string weight_scale_name(const std::string& key);
inline constexpr const char* kQuantizationPrefix = "quantization.";

}  // namespace pillarseg
