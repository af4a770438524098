// Agreement with PyTorch. tests/golden/*.safetensors each hold a tiny PillarSegNet built in
// PyTorch by tests/golden/make_golden.py (the authors' module names, so the same parameter
// names), its random weights and inputs, and what PyTorch computed from them in float64:
// training-mode logits (B, 12, H, W), the loss, every parameter gradient, the running
// statistics, eval-mode logits, and the state after two AdamW steps. Here the engine builds
// the model from the file's config, loads the weights by name, runs the same steps in float32
// on the CPU reference backend (host/ alone; the fast paths of the CPU backend, Winograd
// convolutions and fused eval blocks, are checked against it in test_model and test_cpu_fast)
// and compares every tensor element-wise (|a - b| <= atol + rtol * |b|,
// worst element reported). The files cover pillars (bilinear, CE, depth 3), pillars + 2D
// observability (bilinear, BCE), pillars + 3D occupancy (transposed convolutions, CE) and the
// grid-map baseline (bilinear, BCE), on odd grid sizes where pooling floors and Up pads.
#include <gtest/gtest.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "engine/model/architecture.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "tests/support/test_support.hpp"
#include "weights_io/safetensors.hpp"

using namespace pillarseg;
using weights::ExpectedTensor;
using weights::SafeTensors;
using weights::ValueKind;

namespace {

// Tolerances. The references are float64; the engine runs in float32, so the differences are
// the engine's rounding. In brackets: the worst measured over the four files, as the atol
// that would just pass (with the rtol given).
struct Tolerance {
  double atol, rtol;
};
// Logits of magnitude ~3: training mode normalises by the batch statistics of a tiny batch,
// which amplifies rounding through each of the U-Net's BatchNorms [7e-7; eval mode 7e-8].
constexpr Tolerance kLogits{3e-6, 1e-5};
constexpr Tolerance kLoss{1e-6, 1e-6};
// One momentum update of means and variances of magnitude ~1 [within the rtol: 1 ulp].
constexpr Tolerance kRunningStatistics{1e-6, 1e-6};
// A gradient element is a sum over thousands of cells of terms of both signs, so its error
// scales with the tensor's largest element rather than with its own: atol is this fraction of
// max |reference| of the tensor [2.3e-6, the PFN's BatchNorm weight].
constexpr double kGradientAtolOfScale = 1e-5;
constexpr double kGradientRtol = 1e-4;
// The bias of a convolution followed by a training-mode BatchNorm has gradient 0 in exact
// arithmetic (the BatchNorm subtracts every per-channel constant); the engine's float32 value
// is rounding noise, bounded by this fraction of the largest gradient in the model [8e-8].
constexpr double kZeroGradientOfScale = 5e-7;
// After two AdamW steps with lr 1e-2 (steps of ~1e-2 on values of ~0.1). Adam normalises each
// element's step, so an element whose gradient is far below its tensor's scale, where the
// gradient's absolute rounding is relatively large, gets a step whose size carries that
// rounding [7e-7; the largest differences, 1e-6, are on elements with gradients below 1e-5].
constexpr Tolerance kAfterAdam{4e-6, 1e-5};
// Adam's moments are running averages of the gradients and their squares: the gradients' rule
// [9.2e-7 for m, 4e-9 for v].
constexpr double kMomentAtolOfScale = 1e-5;
constexpr double kMomentRtol = 1e-4;

std::filesystem::path golden_path(const std::string& stem) {
  return std::filesystem::path(PILLARSEG_SOURCE_DIR) / "tests" / "golden" / (stem + ".safetensors");
}

// Every key of a golden file is under one of these (make_golden.py's documentation).
constexpr std::array<const char*, 7> kSections = {"param.",      "input.",  "out.",   "grad.",
                                                  "after_adam.", "adam_m.", "adam_v."};

// One golden file, parsed: the model config, the loss, AdamW's settings and the inputs.
struct Golden {
  SafeTensors file;
  ModelConfig config;
  LossKind loss = LossKind::CrossEntropy;
  AdamOptions adam;
  int adam_steps = 0;
  ModelBatch batch;
  Tensor<uint8_t> labels;  // (B, H, W)
  std::array<float, 13> coefficients{};
};

const std::string& metadata(const SafeTensors& file, const std::string& key) {
  const auto it = file.metadata.find(key);
  PS_CHECK(it != file.metadata.end(), "{}: __metadata__ has no \"{}\"", file.source(), key);
  return it->second;
}

Golden load_golden(const std::string& stem) {
  Golden g;
  g.file = SafeTensors::read(golden_path(stem));
  const SafeTensors& f = g.file;
  for (const std::string& name : f.names()) {
    const bool known = std::any_of(kSections.begin(), kSections.end(),
                                   [&](const char* prefix) { return name.rfind(prefix, 0) == 0; });
    PS_CHECK(known, "{}: tensor \"{}\" is in no section this test knows", f.source(), name);
  }
  g.config = model_config_from_yaml(YAML::Load(metadata(f, "config")), f.source());
  const std::string& loss = metadata(f, "loss");
  PS_CHECK(loss == "ce" || loss == "bce", "{}: loss must be ce or bce, got {}", f.source(), loss);
  g.loss = loss == "ce" ? LossKind::CrossEntropy : LossKind::Bce;
  g.adam.lr = std::stof(metadata(f, "lr"));
  g.adam.beta1 = std::stof(metadata(f, "beta1"));
  g.adam.beta2 = std::stof(metadata(f, "beta2"));
  g.adam.eps = std::stof(metadata(f, "eps"));
  g.adam.weight_decay = std::stof(metadata(f, "weight_decay"));
  g.adam_steps = std::stoi(metadata(f, "adam_steps"));

  const std::vector<int64_t> labels = f.get_i64("input.labels");
  g.labels = Tensor<uint8_t>(f.at("input.labels").shape);
  for (size_t i = 0; i < labels.size(); ++i) {
    PS_CHECK(labels[i] >= 0 && labels[i] <= 12, "{}: label {} is not a class id 0..12", f.source(),
             labels[i]);
    g.labels[static_cast<int64_t>(i)] = static_cast<uint8_t>(labels[i]);
  }
  const Tensor<float> coefficients = f.get_f32("input.coefficients", {13});
  std::copy(coefficients.begin(), coefficients.end(), g.coefficients.begin());

  g.batch.batch = static_cast<int>(g.labels.dim(0));
  if (g.config.pillar_input) {
    g.batch.pillar_points = f.get_f32("input.pillar_points");
    const std::vector<int64_t> cells = f.get_i64("input.pillar_cells");
    g.batch.pillar_cells = Tensor<int32_t>(f.at("input.pillar_cells").shape);
    for (size_t i = 0; i < cells.size(); ++i)
      g.batch.pillar_cells[static_cast<int64_t>(i)] = static_cast<int32_t>(cells[i]);
  }
  if (g.config.occupancy != OccupancyInput::None) g.batch.occupancy = f.get_f32("input.occupancy");
  if (g.config.grid_map_input) g.batch.grid_map = f.get_f32("input.grid_map");
  return g;
}

// Which of the model's tensors a section holds: trainable parameters, running statistics (F32)
// and num_batches_tracked counters (I64, shape ()).
enum Kinds {
  kTrainable = 1,
  kBuffers = 2,
  kCounters = 4,
  kState = kTrainable | kBuffers | kCounters
};

std::vector<ExpectedTensor> expected_tensors(const ParameterSet& ps, int kinds) {
  std::vector<ExpectedTensor> out;
  for (const ParamEntry& e : ps.entries())
    if (kinds & (e.trainable ? kTrainable : kBuffers))
      out.push_back({e.name, e.shape, ValueKind::Float});
  if (kinds & kCounters)
    for (const auto& [name, count] : ps.counters()) out.push_back({name, {}, ValueKind::Integer});
  return out;
}

// The tensors under `prefix`, named without it. They must be exactly the model's tensors of
// `kinds` with the model's shapes: a missing, extra or misshapen name throws, listing them all.
SafeTensors section(const Golden& g, const ParameterSet& ps, const std::string& prefix, int kinds) {
  SafeTensors s;
  for (const std::string& name : g.file.names()) {
    if (name.rfind(prefix, 0) != 0) continue;
    weights::TensorRecord record = g.file.at(name);
    record.name = name.substr(prefix.size());
    s.add(std::move(record));
  }
  weights::check_names_and_shapes(s, expected_tensors(ps, kinds),
                                  g.file.source() + ", section " + prefix);
  return s;
}

// The engine's model of a golden file, with the file's initial weights and counters.
std::unique_ptr<PillarSegNet> build(const Golden& g, Backend& backend) {
  auto net = std::make_unique<PillarSegNet>(g.config, backend);
  ParameterSet& ps = net->parameters();
  const SafeTensors state = section(g, ps, "param.", kState);
  for (size_t i = 0; i < ps.entries().size(); ++i)
    ps.upload(static_cast<int>(i), state.get_f32(ps.entries()[i].name));
  for (auto& [name, count] : ps.counters()) count = state.get_i64(name).at(0);
  return net;
}

// A convolution bias that feeds a training-mode BatchNorm (DoubleConv's convolutions 0 and 3).
bool bias_before_batchnorm(const std::string& name) {
  const auto ends_with = [&](const std::string& suffix) {
    return name.size() >= suffix.size() &&
           name.compare(name.size() - suffix.size(), suffix.size(), suffix) == 0;
  };
  return ends_with(".double_conv.0.bias") || ends_with(".double_conv.3.bias");
}

double max_abs(const Tensor<float>& t) {
  double m = 0;
  for (float x : t) m = std::max(m, double{std::abs(x)});
  return m;
}

// A slice of one of the ParameterSet's flat arrays (gradients, Adam moments) as a tensor.
Tensor<float> slice(const std::vector<float>& flat, const ParamEntry& e) {
  Tensor<float> t(e.shape);
  std::copy_n(flat.begin() + e.offset, t.numel(), t.begin());
  return t;
}

void expect_close(const std::string& what, const Tensor<float>& actual,
                  const Tensor<float>& expected, Tolerance t) {
  EXPECT_TRUE(test::all_close(actual, expected, t.atol, t.rtol)) << what;
}

void expect_close(const std::string& what, double actual, const Tensor<float>& expected,
                  Tolerance t) {
  ASSERT_EQ(expected.numel(), 1) << what;
  EXPECT_NEAR(actual, expected[0], t.atol + t.rtol * std::abs(expected[0])) << what;
}

class GoldenTest : public ::testing::TestWithParam<const char*> {};

TEST_P(GoldenTest, TrainingStepAndEvalMatchPyTorch) {
  const Golden g = load_golden(GetParam());
  auto backend = make_cpu_reference_backend();
  auto net = build(g, *backend);
  ParameterSet& ps = net->parameters();

  net->forward(g.batch, /*training=*/true);
  expect_close("training logits", net->download_logits(), g.file.get_f32("out.logits_train"),
               kLogits);
  expect_close("loss", net->loss(g.labels, g.loss, g.coefficients), g.file.get_f32("out.loss"),
               kLoss);
  net->backward();

  const SafeTensors reference = section(g, ps, "grad.", kTrainable);
  const std::vector<float> grads = ps.download_flat(ps.grads());
  double model_scale = 0;
  for (const ParamEntry& e : ps.entries())
    if (e.trainable) model_scale = std::max(model_scale, max_abs(reference.get_f32(e.name)));
  ASSERT_GT(model_scale, 0) << "all reference gradients are zero: the file cannot test anything";
  int compared = 0;
  for (const ParamEntry& e : ps.entries()) {
    if (!e.trainable) continue;
    const Tensor<float> expected = reference.get_f32(e.name);
    if (bias_before_batchnorm(e.name)) {
      expect_close("grad." + e.name + " (0 in exact arithmetic)", slice(grads, e), expected,
                   {kZeroGradientOfScale * model_scale, 0});
    } else {
      expect_close("grad." + e.name, slice(grads, e), expected,
                   {kGradientAtolOfScale * max_abs(expected), kGradientRtol});
    }
    ++compared;
  }
  EXPECT_GT(compared, 20);

  const SafeTensors buffers = section(g, ps, "out.buffer.", kBuffers | kCounters);
  for (size_t i = 0; i < ps.entries().size(); ++i) {
    const ParamEntry& e = ps.entries()[i];
    if (!e.trainable)
      expect_close("out.buffer." + e.name, ps.download(static_cast<int>(i)),
                   buffers.get_f32(e.name), kRunningStatistics);
  }
  for (const auto& [name, count] : ps.counters())
    EXPECT_EQ(count, buffers.get_i64(name).at(0)) << name;

  net->forward(g.batch, /*training=*/false);
  expect_close("eval logits", net->download_logits(), g.file.get_f32("out.logits_eval"), kLogits);
}

// Two AdamW steps (decoupled weight decay, bias correction), the gradient recomputed by a
// training forward before the second. The biases before a BatchNorm get gradient 0 here, their
// exact value: Adam divides by sqrt(v) + eps with eps = 1e-8, which turns float32 rounding
// noise of ~1e-9 into steps of up to lr in either direction (in PyTorch's float32 as much as
// here), and those steps would also shift the next BatchNorm's running mean. With the exact
// gradient, the reference and the engine agree to rounding.
TEST_P(GoldenTest, TwoAdamStepsMatchPyTorch) {
  const Golden g = load_golden(GetParam());
  auto backend = make_cpu_reference_backend();
  auto net = build(g, *backend);
  ParameterSet& ps = net->parameters();
  ASSERT_EQ(g.adam_steps, 2);
  for (int step = 1; step <= g.adam_steps; ++step) {
    net->forward(g.batch, /*training=*/true);
    const double loss = net->loss(g.labels, g.loss, g.coefficients);
    if (step == 2)
      expect_close("loss after one step", loss, g.file.get_f32("out.loss_step2"), kLoss);
    net->backward();
    for (size_t i = 0; i < ps.entries().size(); ++i) {
      if (!bias_before_batchnorm(ps.entries()[i].name)) continue;
      Ref grad = ps.grad(static_cast<int>(i));
      backend->fill_zero(grad.data, grad.bytes());
    }
    Ref values = ps.values(), m = ps.adam_m(), v = ps.adam_v();
    backend->adam_step(values, ps.grads(), m, v, step, g.adam);
  }

  const SafeTensors state = section(g, ps, "after_adam.", kState);
  const SafeTensors adam_m = section(g, ps, "adam_m.", kTrainable);
  const SafeTensors adam_v = section(g, ps, "adam_v.", kTrainable);
  const std::vector<float> m = ps.download_flat(ps.adam_m()), v = ps.download_flat(ps.adam_v());
  for (size_t i = 0; i < ps.entries().size(); ++i) {
    const ParamEntry& e = ps.entries()[i];
    expect_close("after_adam." + e.name, ps.download(static_cast<int>(i)), state.get_f32(e.name),
                 e.trainable ? kAfterAdam : kRunningStatistics);
    if (!e.trainable || bias_before_batchnorm(e.name)) continue;
    const Tensor<float> expected_m = adam_m.get_f32(e.name), expected_v = adam_v.get_f32(e.name);
    expect_close("adam_m." + e.name, slice(m, e), expected_m,
                 {kMomentAtolOfScale * max_abs(expected_m), kMomentRtol});
    expect_close("adam_v." + e.name, slice(v, e), expected_v,
                 {kMomentAtolOfScale * max_abs(expected_v), kMomentRtol});
  }
  for (const auto& [name, count] : ps.counters())
    EXPECT_EQ(count, state.get_i64(name).at(0)) << name;
}

constexpr std::array<const char*, 4> kFiles = {"pillars_bilinear_ce", "pillars_occ2d_bilinear_bce",
                                               "pillars_occ3d_transposed_ce",
                                               "gridmap_bilinear_bce"};

INSTANTIATE_TEST_SUITE_P(Variants, GoldenTest, ::testing::ValuesIn(kFiles));

// The weights-only file beside each golden file, as a PyTorch user exports a model (the
// state_dict, no metadata; make_golden.py writes it), opens without a config: the architecture
// comes from its tensor shapes (engine/model/architecture.hpp), on the paper's grid unless its
// occupancy stream reads a number of layers that grid does not have, and its weights are the
// golden file's: the same eval logits, bit for bit, on the golden file's grid.
TEST_P(GoldenTest, WeightsOnlyFileOpensWithoutAConfig) {
  const Golden g = load_golden(GetParam());
  const std::filesystem::path path = golden_path(std::string("weights_only_") + GetParam());
  const Checkpoint checkpoint = read_checkpoint(path);
  EXPECT_FALSE(checkpoint.config.has_value());
  EXPECT_TRUE(checkpoint.file.metadata.empty());
  ModelConfig inferred;
  if (g.config.occupancy == OccupancyInput::Occupancy3D) {
    try {
      config_for(checkpoint, "");
      FAIL() << "a stream of " << g.config.grid.layers() << " layers fits the paper's grid of 20";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("occupancy.conv.weight has 4 input channels"), std::string::npos)
          << e.what();
    }
    inferred = model_config_from_tensors(checkpoint.file, g.config.grid);
  } else {
    inferred = config_for(checkpoint, "").model;
    EXPECT_EQ(inferred.grid, GridSpec{});
  }
  EXPECT_EQ(inferred.pillar_input, g.config.pillar_input);
  if (g.config.pillar_input) {
    EXPECT_EQ(inferred.pillar_channels, g.config.pillar_channels);
  }
  EXPECT_EQ(inferred.occupancy, g.config.occupancy);
  if (g.config.occupancy != OccupancyInput::None) {
    EXPECT_EQ(inferred.occupancy_channels, g.config.occupancy_channels);
  }
  EXPECT_EQ(inferred.grid_map_input, g.config.grid_map_input);
  EXPECT_EQ(inferred.base_width, g.config.base_width);
  EXPECT_EQ(inferred.depth, g.config.depth);
  EXPECT_EQ(inferred.transposed, g.config.transposed);

  ModelConfig on_golden_grid = inferred;
  on_golden_grid.grid = g.config.grid;
  on_golden_grid.max_points_per_pillar = g.config.max_points_per_pillar;  // no tensor holds N
  auto backend = make_cpu_reference_backend();
  PillarSegNet loaded(on_golden_grid, *backend);
  load_weights(checkpoint, loaded, /*with_optimizer=*/false);
  auto reference = build(g, *backend);
  loaded.forward(g.batch, false);
  reference->forward(g.batch, false);
  EXPECT_EQ(loaded.download_logits(), reference->download_logits());
}

// A file whose shapes fit no PillarSegNet gets an error naming the tensor that does not fit.
TEST(Golden, ShapesThatFitNoArchitectureNameTheTensor) {
  const Checkpoint good = read_checkpoint(golden_path("weights_only_pillars_bilinear_ce"));
  const auto message_without = [&](const std::string& dropped, const std::string& replaced = "",
                                    Shape replacement = {}) {
    SafeTensors file;
    for (const std::string& name : good.file.names()) {
      if (name == dropped) continue;
      weights::TensorRecord record = good.file.at(name);
      if (name == replaced) {
        record.shape = replacement;
        record.bytes.assign(static_cast<size_t>(shape_numel(replacement)) * 4, 0);
      }
      file.add(std::move(record));
    }
    try {
      model_config_from_tensors(file);
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string("(no error)");
  };
  EXPECT_NE(message_without("segmentation_head.outc.conv.weight").find("no tensor segmentation_head.outc.conv.weight"),
            std::string::npos);
  EXPECT_NE(message_without("", "vfe.pfn_layers.0.linear.weight", {4, 9}).find("expected (C, 10)"),
            std::string::npos);
  EXPECT_NE(message_without("", "segmentation_head.down1.maxpool_conv.1.double_conv.0.weight", {8, 5, 3, 3})
                .find("reads 5 input channels, but the streams give 4"),
            std::string::npos);
  EXPECT_NE(message_without("", "segmentation_head.outc.conv.weight", {11, 4, 1, 1}).find("expected (12, b, 1, 1)"),
            std::string::npos);
  // A tensor the inferred model does not have: load_weights names it.
  SafeTensors extra = good.file;
  extra.add_f32("segmentation_head.extra.weight", Tensor<float>({2}));
  const ModelConfig c = model_config_from_tensors(extra);
  auto backend = make_cpu_reference_backend();
  PillarSegNet net(c, *backend);
  Checkpoint with_extra;
  with_extra.file = extra;
  try {
    load_weights(with_extra, net, false);
    FAIL() << "an extra tensor must be reported";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("segmentation_head.extra.weight"), std::string::npos) << e.what();
  }
}



// The files cover every input stream, both upsamplings and both losses, on grids whose sides
// pooling does not halve evenly (so that some Up pads), with unlabelled cells in the labels.
TEST(Golden, FilesCoverTheVariants) {
  std::set<OccupancyInput> occupancy;
  std::set<bool> transposed, grid_map, pillars;
  std::set<LossKind> losses;
  for (const char* stem : kFiles) {
    const Golden g = load_golden(stem);
    occupancy.insert(g.config.occupancy);
    transposed.insert(g.config.transposed);
    grid_map.insert(g.config.grid_map_input);
    pillars.insert(g.config.pillar_input);
    losses.insert(g.loss);
    const int H = g.config.grid.height(), W = g.config.grid.width(), levels = 1 << g.config.depth;
    EXPECT_TRUE(H % levels != 0 && W % levels != 0) << stem << ": " << W << " x " << H;
    EXPECT_GE(g.batch.batch, 2) << stem;
    EXPECT_TRUE(std::count(g.labels.begin(), g.labels.end(), uint8_t{0}) > 0) << stem;
    if (g.config.pillar_input) {
      EXPECT_GT(g.batch.pillar_points.dim(0), 0) << stem;
    }
  }
  EXPECT_EQ(occupancy.size(), 3u);
  EXPECT_EQ(transposed.size(), 2u);
  EXPECT_EQ(grid_map.size(), 2u);
  EXPECT_EQ(pillars.size(), 2u);
  EXPECT_EQ(losses.size(), 2u);
}

// The comparison has teeth: a file whose weights lack one of the model's names, or hold one it
// does not have, is refused with both names; and a change of 1e-3 to one weight deep in the
// U-Net moves the logits beyond the tolerance.
TEST(Golden, MissingOrExtraNamesAndAWrongWeightAreCaught) {
  const Golden g = load_golden(kFiles[0]);
  auto backend = make_cpu_reference_backend();
  auto net = build(g, *backend);
  const std::string dropped = "param.segmentation_head.up1.conv.double_conv.3.weight";
  Golden broken;
  broken.file.metadata = g.file.metadata;
  for (const std::string& name : g.file.names())
    if (name != dropped) broken.file.add(g.file.at(name));
  weights::TensorRecord extra = g.file.at("param.segmentation_head.outc.conv.bias");
  extra.name = "param.segmentation_head.outc.conv.bias_typo";
  broken.file.add(extra);
  try {
    section(broken, net->parameters(), "param.", kState);
    ADD_FAILURE() << "a missing and an extra weight were accepted";
  } catch (const Error& e) {
    const std::string message = e.what();
    EXPECT_NE(message.find("missing segmentation_head.up1.conv.double_conv.3.weight"),
              std::string::npos)
        << message;
    EXPECT_NE(message.find("unexpected segmentation_head.outc.conv.bias_typo"), std::string::npos)
        << message;
  }

  ParameterSet& ps = net->parameters();
  const int index = ps.find("segmentation_head.down2.maxpool_conv.1.double_conv.3.weight");
  ASSERT_GE(index, 0);
  Tensor<float> weight = ps.download(index);
  weight[0] += 1e-3f;
  ps.upload(index, weight);
  net->forward(g.batch, /*training=*/true);
  EXPECT_FALSE(test::all_close(net->download_logits(), g.file.get_f32("out.logits_train"),
                               kLogits.atol, kLogits.rtol));
}

}  // namespace
