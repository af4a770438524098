// INT8 inference of the whole model (DESIGN.md section 10): the calibration's rule by hand, the
// model's INT8 graph on the CPU backend (the VNNI and AMX-INT8 instruction models, and the native
// instructions where this CPU has them) and on the CUDA backend's emulation (mma.sync m16n8k32)
// against each other and against FP32, the scales in a checkpoint, and the errors a user meets.
#include <gtest/gtest.h>

#include <cmath>
#include <map>
#include <string>
#include <vector>

#include "engine/cpu/int8_conv.hpp"
#include "engine/cuda/cuda_backend.hpp"
#include "engine/model/calibration.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/model_graph.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "tests/support/test_support.hpp"
#include "tests/support/tiny_model.hpp"

using namespace pillarseg;

namespace {

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "no error";
}

double nmse(const Tensor<float>& a, const Tensor<float>& r) {
  double num = 0, den = 0;
  for (int64_t i = 0; i < r.numel(); ++i) {
    const double e = static_cast<double>(a.data()[i]) - r.data()[i];
    num += e * e, den += static_cast<double>(r.data()[i]) * r.data()[i];
  }
  return num / den;
}

double agreement(const Tensor<uint8_t>& a, const Tensor<uint8_t>& b) {
  int64_t same = 0;
  for (int64_t i = 0; i < a.numel(); ++i) same += a.data()[i] == b.data()[i];
  return static_cast<double>(same) / static_cast<double>(a.numel());
}

// A few training steps so that the BatchNorms' statistics are the data's, then the scales of the
// U-Net's inputs from FP32 evaluation forwards of the two batches.
std::map<std::string, Int8Input> train_and_calibrate(PillarSegNet& net, Backend& backend,
                                                 const std::vector<test::TinyData>& data) {
  for (int64_t step = 1; step <= 3; ++step) {
    net.parameters().zero_grads();
    net.forward(data[0].batch, true);
    net.loss(data[0].labels, LossKind::CrossEntropy, test::kCoefficients);
    net.backward();
    AdamOptions adam;
    adam.lr = 1e-2;
    Ref values = net.parameters().values(), m = net.parameters().adam_m(), v = net.parameters().adam_v();
    backend.adam_step(values, net.parameters().grads(), m, v, step, adam);
  }
  InputScaleCalibrator calibrator;
  {
    const CalibrationScope observing(net, calibrator);
    for (const test::TinyData& d : data) net.forward(d.batch, false);
  }
  EXPECT_EQ(calibrator.forwards("segmentation_head.down1.maxpool_conv.1.double_conv.0"), 2);
  return calibrator.inputs();
}

}  // namespace

// Nearest rank over |v|, NaN skipped: of 0..99 (and -100) the 99th percentile is 98, the 100th
// 100, the 50th 49. An input with a negative value seen is signed (/ 127), one never negative
// unsigned (/ 255).
TEST(Int8Calibration, PercentileAndScaleByHand) {
  std::vector<float> v;
  for (int i = 0; i < 100; ++i) v.push_back(static_cast<float>(i));
  v[0] = -100.0f;  // |v| = 100, 1..99
  v.push_back(std::numeric_limits<float>::quiet_NaN());
  EXPECT_EQ(abs_percentile(v, 100), 100.0f);
  EXPECT_EQ(abs_percentile(v, 99), 99.0f);   // rank ceil(0.99 100) = 99 of 1..99, 100
  EXPECT_EQ(abs_percentile(v, 50), 50.0f);   // rank 50
  EXPECT_EQ(abs_percentile(std::vector<float>{}, 99), 0.0f);
  InputScaleCalibrator c(100);
  c.add("a", std::vector<float>{1, -254});
  c.add("a", std::vector<float>{127});
  c.add("zero", std::vector<float>{0, 0});
  c.add("relu", std::vector<float>{0, 51, 255});
  c.add("relu", std::vector<float>{510, 0});
  const auto inputs = c.inputs();
  EXPECT_EQ(inputs.at("a").scale, 2.0f);  // the largest over the forwards, / 127
  EXPECT_FALSE(inputs.at("a").non_negative);
  EXPECT_EQ(inputs.at("relu").scale, 2.0f);  // 510 / 255
  EXPECT_TRUE(inputs.at("relu").non_negative);
  EXPECT_EQ(inputs.at("zero").scale, 1e-8f);
  EXPECT_TRUE(inputs.at("zero").non_negative);
  EXPECT_EQ(c.forwards("a"), 2);
  EXPECT_NE(error_of([] { InputScaleCalibrator bad(0); }).find("percentile"), std::string::npos);
  EXPECT_EQ(input_scale_name("x.double_conv.0"), "quantization.x.double_conv.0.input_scale");
  EXPECT_EQ(input_non_negative_name("x.double_conv.0"), "quantization.x.double_conv.0.input_non_negative");
}

// The model in INT8: the same bits on the CPU's VNNI and AMX-INT8 models and on the CUDA
// backend's mma.sync emulation (one quantization rule, exact integer sums, one epilogue; the
// FP32 head's sums in another order on the CUDA backend: within 1e-10 NMSE of each other); within
// what INT8 costs of FP32 (NMSE below 1e-3: 127 levels an input and a weight; measured 1e-4 to
// 3e-4) and not equal to it; every U-Net convolution quantized, the head and the occupancy
// stream's in FP32. Every input is calibrated non-negative but the concatenations that hold a
// transposed convolution's output (no activation), and the unsigned bytes halve the error of
// quantizing the same inputs signed.
TEST(Int8Model, TracksFp32TheSameOnEveryBackend) {
  for (const auto& [occupancy, transposed] : std::vector<std::pair<OccupancyInput, bool>>{
           {OccupancyInput::Occupancy3D, false}, {OccupancyInput::None, true}}) {
    SCOPED_TRACE(transposed ? "transposed, pillars alone" : "bilinear, 3d occupancy");
    const ModelConfig c = test::tiny_config(occupancy, transposed);
    const std::vector<test::TinyData> data = {test::tiny_data(c, 2, 23, 0.4), test::tiny_data(c, 2, 24, 0.4)};
    auto vnni_model = make_cpu_backend_emulated_bf16(/*amx=*/false);
    PillarSegNet net(c, *vnni_model, 3);
    const std::map<std::string, Int8Input> scales = train_and_calibrate(net, *vnni_model, data);
    // Every U-Net convolution: 2 per level of the encoder and the decoder (+ the transposed ups).
    EXPECT_EQ(scales.size(), static_cast<size_t>(4 * c.depth + (transposed ? c.depth : 0)));
    int signed_inputs = 0;
    for (const auto& [key, input] : scales) {
      signed_inputs += !input.non_negative;
      EXPECT_EQ(input.non_negative, !(transposed && key.ends_with(".conv.double_conv.0") &&
                                      key.find(".up") != std::string::npos))
          << key;
    }
    EXPECT_EQ(signed_inputs, transposed ? c.depth : 0);
    net.forward(data[1].batch, false);
    const Tensor<float> fp32 = net.download_logits();
    const Tensor<uint8_t> labels32 = net.predict_labels();
    net.set_int8_inputs(scales);
    net.set_precision(Precision::I8);
    net.forward(data[1].batch, false);
    const Tensor<float> int8 = net.download_logits();
    int quantized = 0, fp32_convs = 0;
    for (const GraphNode& n : net.graph(false).nodes()) {
      if (n.op == OpKind::PreparedConv2d || n.op == OpKind::PreparedConvTranspose2d) {
        ++quantized;
        EXPECT_EQ(op_label(net.graph(false), n).substr(0, 2), "co");
        EXPECT_NE(op_label(net.graph(false), n).find(" i8"), std::string::npos) << n.name;
        EXPECT_GT(n.int8_input.scale, 0.0f);
      }
      fp32_convs += n.op == OpKind::Conv2d || n.op == OpKind::Conv2dBnReluEval;
    }
    EXPECT_EQ(quantized, static_cast<int>(scales.size()));
    EXPECT_EQ(fp32_convs, occupancy == OccupancyInput::None ? 1 : 2);  // the head (and the occupancy stream)
    const double against_fp32 = nmse(int8, fp32);
    RecordProperty("nmse_int8", fmt::format("{:.3g}", against_fp32));
    EXPECT_LT(against_fp32, 1e-3);
    EXPECT_GT(against_fp32, 0.0) << "INT8 must round something";
    EXPECT_GE(agreement(net.predict_labels(), labels32), 0.95);
    // The same ranges quantized signed: 127 levels where the unsigned bytes have 255.
    std::map<std::string, Int8Input> all_signed = scales;
    for (auto& [key, input] : all_signed)
      if (input.non_negative) input = Int8Input{.scale = input.scale * 255.0f / 127.0f, .non_negative = false};
    net.set_int8_inputs(all_signed);
    net.forward(data[1].batch, false);
    const double signed_nmse = nmse(net.download_logits(), fp32);
    RecordProperty("nmse_int8_all_signed", fmt::format("{:.3g}", signed_nmse));
    if (!transposed) {
      EXPECT_LT(against_fp32, 0.75 * signed_nmse);
    }
    net.set_int8_inputs(scales);

    const auto int8_logits = [&](Backend& be) {
      PillarSegNet other(c, be, 3);
      other.parameters().copy_values_from(net.parameters());
      other.set_int8_inputs(scales);
      other.set_precision(Precision::I8);
      other.forward(data[1].batch, false);
      return other.download_logits();
    };
    auto amx_model = make_cpu_backend_emulated_bf16(/*amx=*/true);
    EXPECT_EQ(int8_logits(*amx_model), int8) << "AMX-INT8's model: the same integer sums";
    if (cpu::avx512_vnni_available()) {
      auto native = make_cpu_backend();
      EXPECT_EQ(int8_logits(*native), int8) << "this CPU's instructions: the same bits as their models";
    }
    CudaBackend cuda_backend;
    const double against_cuda = nmse(int8_logits(cuda_backend), int8);
    RecordProperty("nmse_cuda_vs_cpu_int8", fmt::format("{:.3g}", against_cuda));
    EXPECT_LT(against_cuda, 1e-10);
  }
}

// The scales travel in the checkpoint: a calibrated file loads as FP32 (the quantization tensors
// are not model tensors) and sets the model's scales; INT8 without them names the convolution and
// the command that writes them; training refuses INT8.
TEST(Int8Model, ScalesInTheCheckpointAndTheErrors) {
  const ModelConfig c = test::tiny_config();
  auto backend = make_cpu_backend_emulated_bf16();
  PillarSegNet net(c, *backend, 5);
  const test::TinyData d = test::tiny_data(c, 1, 7, 0.4);
  net.set_precision(Precision::I8);
  EXPECT_NE(error_of([&] { net.forward(d.batch, false); })
                .find("precision int8: no input scale for the convolution segmentation_head.down1.maxpool_conv.1."
                      "double_conv.0 (the weights are not calibrated: pillarseg calibrate"),
            std::string::npos);
  EXPECT_NE(error_of([&] { net.set_int8_inputs({{"x", Int8Input{.scale = -1.0f}}}); }).find("not a positive number"),
            std::string::npos);

  const auto path = test::temp_dir() / "calibrated.safetensors";
  RunConfig config;
  config.model = c;
  save_checkpoint(path, net, config, TrainState{}, false);
  weights::SafeTensors file = weights::SafeTensors::read(path);
  Tensor<float> scale({1});
  scale.data()[0] = 0.25f;
  file.add_f32(input_scale_name("segmentation_head.down1.maxpool_conv.1.double_conv.0"), scale);
  file.add_f32(weight_scale_name("segmentation_head.down1.maxpool_conv.1.double_conv.0"), Tensor<float>({4}));
  Tensor<float> one({1});
  one.data()[0] = 1.0f;
  file.add_f32(input_scale_name("segmentation_head.down1.maxpool_conv.1.double_conv.3"), scale);
  file.add_f32(input_non_negative_name("segmentation_head.down1.maxpool_conv.1.double_conv.3"), one);
  file.write(path);
  PillarSegNet loaded(c, *backend, 9);
  load_weights(read_checkpoint(path), loaded, false);  // FP32: the extra tensors are skipped
  EXPECT_EQ(loaded.int8_inputs().size(), 2u);
  const Int8Input first = loaded.int8_inputs().at("segmentation_head.down1.maxpool_conv.1.double_conv.0");
  const Int8Input second = loaded.int8_inputs().at("segmentation_head.down1.maxpool_conv.1.double_conv.3");
  EXPECT_EQ(first.scale, 0.25f);
  EXPECT_FALSE(first.non_negative);  // no input_non_negative: signed
  EXPECT_EQ(second.scale, 0.25f);
  EXPECT_TRUE(second.non_negative);
  EXPECT_EQ(loaded.parameters().download(0), net.parameters().download(0));

  CudaBackend cuda_backend;
  PillarSegNet trained(c, cuda_backend, 1);
  EXPECT_NE(error_of([&] { trained.set_training_precision(Precision::I8); }).find("int8 is an inference precision"),
            std::string::npos);
}

// The weight scales the checkpoint records are the backends': max |w'| / 127 per output channel
// of the weights with their BatchNorm folded in, by hand for one channel.
TEST(Int8Calibration, WeightScalesFoldTheBatchNorm) {
  const ModelConfig c = test::tiny_config();
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend, 4);
  ParameterSet& ps = net.parameters();
  const std::string key = "segmentation_head.down1.maxpool_conv.1.double_conv.0";
  const int w = ps.find(key + ".weight"), gamma = ps.find("segmentation_head.down1.maxpool_conv.1.double_conv.1.weight"),
            var = ps.find("segmentation_head.down1.maxpool_conv.1.double_conv.1.running_var");
  Tensor<float> g = ps.download(gamma), v = ps.download(var);
  g.data()[0] = -2.0f, v.data()[0] = 3.0f;
  ps.upload(gamma, g);
  ps.upload(var, v);
  const Tensor<float> weights = ps.download(w);
  const int64_t k = weights.numel() / weights.dim(0);
  float largest = 0;
  for (int64_t j = 0; j < k; ++j) largest = std::max(largest, std::abs(weights.data()[j] * (-2.0f / std::sqrt(3.0f + 1e-5f))));
  const auto scales = int8_weight_scales(ps, {key});
  EXPECT_FLOAT_EQ(scales.at(key)[0], largest / 127.0f);
  EXPECT_EQ(scales.at(key).size(), static_cast<size_t>(weights.dim(0)));
}
