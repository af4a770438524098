// INT8 calibration (DESIGN.md section 10): the per-tensor scale of every U-Net convolution's
// input, from FP32 evaluation forwards over a few scans, and where the scales live in a
// checkpoint.
//
// The rule: a convolution's input scale is the largest, over the calibration scans, of the
// 99.999th percentile of |x| over the input's values, divided by 255 where no input value was
// negative (q = x / scale fills [0, 255]: Int8Input::non_negative, core/dtype.hpp) and by 127
// otherwise (q fills [-127, 127]). In the model every U-Net convolution's input is a ReLU's
// output, max-pooled, bilinear-upsampled or concatenated, so all are non-negative but those
// after a transposed convolution (no activation): unsigned bytes give them twice the levels,
// which the instructions take as they are (VPDPBUSD and AMX multiply unsigned by signed bytes;
// the tensor cores' mma has a u8 x s8 form).
//
// A percentile rather than the maximum: one outlier among tens of millions of values (a pillar
// with an extreme reflectance or height, a ReLU output far in the tail) would otherwise set a
// scale that leaves most values a handful of levels; the 99.999th keeps the range of all but the
// top 0.001%, which saturate. Measured with the demo's model calibrated on simulated scans
// (docs/benchmarks.md#int8), arg-max agreement with FP32 on the cells with points of the real
// scans 99 / kitti_object 004139 / 004747: unsigned inputs, maximum 99.34 / 99.15 / 99.22%,
// 99.999th 99.23 / 99.43 / 99.18%, 99.99th 98.20 / 98.71 / 98.65%; all inputs signed, 99.999th
// 98.97 / 98.91 / 98.55% (maximum 98.56%, 99.9th 94.10% on scan 99): the U-Net's inputs have
// tails that matter, and clipping them costs more than coarser levels. (The entropy (KL) rule of
// TensorRT clips harder still.)
//
// The 3x3 pad-1 convolutions also get the Winograd-domain scales of Int8Input::winograd
// (core/dtype.hpp): per tile position p of F(2x2, 3x3), the largest over the scans of the same
// percentile of |V_p| (host/winograd_f2_stats.hpp), / 127 (V is signed whatever x is). A CPU
// with AVX512-VNNI and no AMX runs the layers where that form pays in it (engine/cpu/int8_conv.hpp);
// the other backends and layers use the per-tensor scale.
//
// In a checkpoint: quantization.<key>.input_scale (1), quantization.<key>.input_non_negative (1:
// 1 or 0; absent means 0), quantization.<key>.winograd_input_scale (16, the 3x3 pad-1
// convolutions'; absent in files calibrated before it, whose layers then run the direct kernel)
// and quantization.<key>.weight_scale (O, the per-output-channel scales max |w'| / 127 of the
// weights with the BatchNorm folded in, for
// inspection: the backends derive them again from the weights), key the convolution's parameter
// prefix ("segmentation_head.down1.maxpool_conv.1.double_conv.0"). Loaders that do not know them
// skip them (engine/model/checkpoint.cpp), so a calibrated file loads as FP32 anywhere.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <span>
#include <string>
#include <vector>

#include "core/dtype.hpp"
#include "core/tensor.hpp"

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
  // ... of a 3x3 pad-1 convolution, x (B, C, H, W): also its Winograd-domain statistics.
  void add_winograd(const std::string& key, std::span<const float> values, const Shape& shape);
  // key -> the input's quantization: non_negative where no value seen was negative, scale the
  // largest percentile seen / 255 (non-negative) or / 127, at least 1e-8 (so that an all-zero
  // input still has a valid scale).
  std::map<std::string, Int8Input> inputs() const;
  int64_t forwards(const std::string& key) const;
  double percentile() const { return percentile_; }

 private:
  double percentile_;
  std::map<std::string, float> largest_;
  std::map<std::string, std::array<float, 16>> largest_winograd_;
  std::map<std::string, bool> negative_;  // whether a negative value was seen
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
std::string input_non_negative_name(const std::string& key);
std::string winograd_input_scale_name(const std::string& key);
inline constexpr const char* kQuantizationPrefix = "quantization.";

}  // namespace pillarseg
