// INT8 inference of the whole model (DESIGN.md section 10): the calibration's rule by hand, the
// model's INT8 graph on the CPU backend (the VNNI and AMX-INT8 instruction models, and the native
// instructions where this CPU has them) and on the CUDA backend's emulation (mma.sync m16n8k32)
// against each other and against FP32, the scales in a checkpoint, and the errors a user meets.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <span>
#include <string>
#include <vector>

#include "engine/cpu/int8_conv.hpp"
#include "engine/cuda/cuda_backend.hpp"
#include "engine/model/calibration.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/model_graph.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "host/softmax.hpp"
#include "host/winograd_f2_stats.hpp"
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

// The class map of logits (B, 12, H, W).
Tensor<uint8_t> class_ids(const Tensor<float>& logits) {
  Tensor<uint8_t> ids;
  host::argmax_class_ids(logits, ids);
  return ids;
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

// The Winograd F(2x2, 3x3) transform's statistics by position: the maxima against V = B^T d B
// worked out with the matrices in double on an odd-sized input (a partial tile at the right and
// bottom, zero outside the image), bit for bit against the kernel's own maxima (the same FP32
// order); the 100th percentile is the maximum, a lower one the upper edge of the histogram bin
// (max / 4096 wide) of the nearest-rank value.
TEST(Int8Calibration, WinogradDomainStatisticsByPosition) {
  const Shape shape{2, 3, 5, 7};
  Rng rng(11);
  Tensor<float> x = test::random_tensor<float>(shape, rng, -2, 3);
  const double bt[4][4] = {{1, 0, -1, 0}, {0, 1, 1, 0}, {0, -1, 1, 0}, {0, 1, 0, -1}};
  std::array<double, 16> expected{};
  std::vector<std::vector<double>> by_position(16);
  for (int64_t plane = 0; plane < 6; ++plane) {
    for (int64_t ty = 0; ty < 3; ++ty) {
      for (int64_t tx = 0; tx < 4; ++tx) {
        double d[4][4];
        for (int r = 0; r < 4; ++r)
          for (int c = 0; c < 4; ++c) {
            const int64_t iy = 2 * ty - 1 + r, ix = 2 * tx - 1 + c;
            d[r][c] = iy < 0 || iy >= 5 || ix < 0 || ix >= 7 ? 0.0 : x.data()[(plane * 5 + iy) * 7 + ix];
          }
        for (int i = 0; i < 4; ++i)
          for (int j = 0; j < 4; ++j) {
            double v = 0;  // (B^T d B)[i][j] = sum_r sum_c bt[i][r] d[r][c] bt[j][c]
            for (int r = 0; r < 4; ++r)
              for (int c = 0; c < 4; ++c) v += bt[i][r] * d[r][c] * bt[j][c];
            expected[static_cast<size_t>(4 * i + j)] = std::max(expected[static_cast<size_t>(4 * i + j)], std::abs(v));
            by_position[static_cast<size_t>(4 * i + j)].push_back(std::abs(v));
          }
      }
    }
  }
  const std::array<float, 16> absmax = host::winograd_f2_input_absmax(x.data(), shape);
  float kernel[16];
  cpu::int8_winograd_input_absmax(ActRef{x.data(), shape, false}, kernel);
  const std::array<float, 16> p100 = host::winograd_f2_input_percentiles(x.data(), shape, 100);
  const std::array<float, 16> p50 = host::winograd_f2_input_percentiles(x.data(), shape, 50);
  for (size_t p = 0; p < 16; ++p) {
    SCOPED_TRACE(p);
    EXPECT_NEAR(absmax[p], expected[p], 1e-5 * expected[p]);
    EXPECT_EQ(absmax[p], kernel[p]);
    EXPECT_EQ(p100[p], absmax[p]);
    std::vector<double>& v = by_position[p];
    ASSERT_EQ(v.size(), 72u);  // 6 planes x 3 x 4 tiles
    std::nth_element(v.begin(), v.begin() + 35, v.end());  // nearest rank ceil(0.5 72) = 36
    EXPECT_GE(p50[p], v[35] - 1e-5 * expected[p]);
    EXPECT_LE(p50[p], v[35] + absmax[p] / 4096.0 + 1e-5 * expected[p]);
  }
  EXPECT_NE(test::error_of([&] { host::winograd_f2_input_percentiles(x.data(), shape, 0); }).find("percentile"),
            std::string::npos);

  // The calibrator: a 3x3 pad-1 convolution's input gets the per-position scales, the largest over
  // the forwards / 127, besides its per-tensor scale; another convolution's none.
  InputScaleCalibrator c(100);
  Tensor<float> half_x = x;
  for (int64_t i = 0; i < half_x.numel(); ++i) half_x.data()[i] *= 0.5f;
  c.add_winograd("conv3", std::span<const float>(half_x.data(), static_cast<size_t>(half_x.numel())), shape);
  c.add_winograd("conv3", std::span<const float>(x.data(), static_cast<size_t>(x.numel())), shape);
  c.add("conv1", std::vector<float>{1, 2});
  const auto inputs = c.inputs();
  ASSERT_TRUE(inputs.at("conv3").has_winograd());
  for (size_t p = 0; p < 16; ++p) EXPECT_EQ(inputs.at("conv3").winograd[p], std::max(absmax[p] / 127.0f, 1e-8f));
  float max_x = 0.0f;
  for (int64_t i = 0; i < x.numel(); ++i) max_x = std::max(max_x, std::abs(x.data()[i]));
  EXPECT_EQ(inputs.at("conv3").scale, max_x / 127.0f);  // signed: x has negative values
  EXPECT_FALSE(inputs.at("conv3").non_negative);
  EXPECT_FALSE(inputs.at("conv1").has_winograd());
  EXPECT_EQ(c.forwards("conv3"), 2);
  EXPECT_EQ(winograd_input_scale_name("x.double_conv.0"), "quantization.x.double_conv.0.winograd_input_scale");
  EXPECT_NE(test::error_of([&] { c.add_winograd("bad", std::vector<float>{1, 2, 3}, {1, 1, 2, 2}); })
                .find("is not (B, C, H, W) with 3 values"),
            std::string::npos);
}

// The model in INT8: the same bits on the CPU's VNNI and AMX-INT8 models, and on the CUDA
// backend's mma.sync emulation the same integer sums of the same quantized inputs (one
// quantization rule, one epilogue), while what the two backends compute in FP32 (the occupancy
// stream's convolutions before the U-Net, the head after it) sums in other orders: an FP32 input
// that lands on a rounding boundary of its quantization can take the next level on one backend,
// so they agree within 1e-6 NMSE (below 1e-10 on an AMD Zen 4, 2.7e-8 on a Zen 3, whose FP32
// convolutions run AVX2 code; a wrong fragment layout or epilogue gives the quantization noise's
// 1e-4 and more) and on the label map; within
// what INT8 costs of FP32 (NMSE below 1e-3: 127 levels an input and a weight; measured 1e-4 to
// 3e-4) and not equal to it; every U-Net convolution quantized, the head on FP32 prepared weights
// reading the U-Net's BF16 last output, the occupancy stream's convolutions in FP32. Every input is calibrated non-negative but the concatenations that hold a
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
    int quantized = 0, fp32_convs = 0, fp32_prepared = 0;
    const Graph& g = net.graph(false);
    for (const GraphNode& n : g.nodes()) {
      if (n.op == OpKind::PreparedConv2d || n.op == OpKind::PreparedConvTranspose2d) {
        const auto& a = n.as<PreparedConv2dArgs>();
        if (g.at(a.prepared).dtype == DType::F32) {  // the head: FP32 weights on the BF16 last output
          ++fp32_prepared;
          EXPECT_EQ(n.stage, Stage::Head) << n.name;
          EXPECT_EQ(g.at(a.x).dtype, DType::BF16) << n.name;
          EXPECT_EQ(g.at(a.y).dtype, DType::F32) << n.name;
          continue;
        }
        ++quantized;
        EXPECT_EQ(op_label(net.graph(false), n, Device::Cpu).substr(0, 2), "co");
        EXPECT_NE(op_label(net.graph(false), n, Device::Cpu).find(" i8"), std::string::npos) << n.name;
        EXPECT_GT(n.int8_input.scale, 0.0f);
      }
      fp32_convs += n.op == OpKind::Conv2d || n.op == OpKind::Conv2dBnReluEval;
    }
    EXPECT_EQ(quantized, static_cast<int>(scales.size()));
    EXPECT_EQ(fp32_prepared, 1);
    EXPECT_EQ(fp32_convs, occupancy == OccupancyInput::None ? 0 : 1);  // the occupancy stream's
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
    const Tensor<float> cuda_int8 = int8_logits(cuda_backend);
    const double against_cuda = nmse(cuda_int8, int8);
    RecordProperty("nmse_cuda_vs_cpu_int8", fmt::format("{:.3g}", against_cuda));
    EXPECT_LT(against_cuda, 1e-6);
    EXPECT_EQ(class_ids(cuda_int8), class_ids(int8));
  }
}

// The Winograd domain on the VNNI kernels (engine/cpu/int8_conv.hpp): calibration gives every 3x3
// pad-1 U-Net convolution its per-position scales; the tiny model's channels are below the
// default rule's 256, so it runs direct (the same bits as without those scales) unless
// PILLARSEG_CPU_INT8_WINOGRAD=1 asks for the Winograd form everywhere: other bits, within what
// the coarser quantization of V costs of FP32 (NMSE 3e-3; measured below 1e-3). The AMX family
// never takes it, and the switch's bad values are named.
TEST(Int8Model, WinogradDomainOnVnniWhereCalibrated) {
  const ModelConfig c = test::tiny_config();
  const std::vector<test::TinyData> data = {test::tiny_data(c, 2, 23, 0.4), test::tiny_data(c, 2, 24, 0.4)};
  auto vnni_model = make_cpu_backend_emulated_bf16(/*amx=*/false);
  PillarSegNet net(c, *vnni_model, 3);
  const std::map<std::string, Int8Input> scales = train_and_calibrate(net, *vnni_model, data);
  std::map<std::string, Int8Input> per_tensor = scales;
  int with_winograd = 0;
  for (auto& [key, input] : per_tensor) {
    EXPECT_TRUE(input.has_winograd()) << key;  // every U-Net convolution here is 3x3 with padding 1
    with_winograd += input.has_winograd();
    input.winograd = {};
  }
  EXPECT_EQ(with_winograd, 4 * c.depth);
  net.forward(data[1].batch, false);
  const Tensor<float> fp32 = net.download_logits();
  const Tensor<uint8_t> labels32 = net.predict_labels();
  const auto int8_logits = [&](Backend& be, const std::map<std::string, Int8Input>& inputs, const char* rule) {
    const test::ScopedEnv env("PILLARSEG_CPU_INT8_WINOGRAD", rule);
    PillarSegNet other(c, be, 3);
    other.parameters().copy_values_from(net.parameters());
    other.set_int8_inputs(inputs);
    other.set_precision(Precision::I8);
    other.forward(data[1].batch, false);
    return std::pair{other.download_logits(), other.predict_labels()};
  };
  const auto [direct, direct_labels] = int8_logits(*vnni_model, per_tensor, nullptr);
  EXPECT_EQ(int8_logits(*vnni_model, scales, nullptr).first, direct) << "below 256 channels: direct";
  EXPECT_EQ(int8_logits(*vnni_model, scales, "0").first, direct);
  const auto [winograd, winograd_labels] = int8_logits(*vnni_model, scales, "1");
  EXPECT_NE(winograd, direct);
  const double winograd_nmse = nmse(winograd, fp32);
  RecordProperty("nmse_int8_winograd", fmt::format("{:.3g}", winograd_nmse));
  RecordProperty("nmse_int8_direct", fmt::format("{:.3g}", nmse(direct, fp32)));
  EXPECT_LT(winograd_nmse, 3e-3);
  EXPECT_GE(agreement(winograd_labels, labels32), 0.93);
  auto amx_model = make_cpu_backend_emulated_bf16(/*amx=*/true);
  EXPECT_EQ(int8_logits(*amx_model, scales, "1").first, direct) << "AMX-INT8: the direct tiles";
  EXPECT_NE(test::error_of([&] { int8_logits(*vnni_model, scales, "yes"); })
                .find("PILLARSEG_CPU_INT8_WINOGRAD must be 0 (the direct INT8 kernel for every convolution) or 1"),
            std::string::npos);
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
  Tensor<float> positions({16});
  for (int p = 0; p < 16; ++p) positions.data()[p] = 0.5f + static_cast<float>(p);
  file.add_f32(winograd_input_scale_name("segmentation_head.down1.maxpool_conv.1.double_conv.3"), positions);
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
  EXPECT_FALSE(first.has_winograd());  // no winograd_input_scale: the direct kernel
  ASSERT_TRUE(second.has_winograd());
  for (int p = 0; p < 16; ++p) EXPECT_EQ(second.winograd[static_cast<size_t>(p)], 0.5f + static_cast<float>(p));
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
