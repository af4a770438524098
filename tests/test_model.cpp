// PillarSegNet on the CPU backend at tiny sizes: parameter names and shapes of the authors'
// model, a whole-model gradient check by finite differences, training reduces the loss, and the
// CPU fast paths (Winograd convolutions, fused eval Conv -> BN -> ReLU, the lifetime-planned
// eval memory) against the reference backend. Memory: gradients and Adam moments allocated on
// first use only; the training step's tensors overlaid by lifetime give the same gradients
// step after step.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <set>
#include <tuple>

#include "core/error.hpp"
#include "core/rng.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "tests/support/test_support.hpp"
#include "tests/support/tiny_model.hpp"

using namespace pillarseg;
using pillarseg::test::kCoefficients;
using pillarseg::test::tiny_config;
using pillarseg::test::tiny_data;
using pillarseg::test::TinyData;

TEST(Model, AuthorsParameterNamesAndShapes) {
  ModelConfig c;  // the paper's full-size model: C = 64, b = 64, bilinear
  c.grid.x_min = 0, c.grid.x_max = 3.2, c.grid.y_min = 0, c.grid.y_max = 3.2;  // small grid; shapes don't depend on it
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend);
  const ParameterSet& ps = net.parameters();
  const auto shape_of = [&](const std::string& name) {
    const int i = ps.find(name);
    EXPECT_GE(i, 0) << name;
    return i >= 0 ? ps.entries()[static_cast<size_t>(i)].shape : Shape{};
  };
  EXPECT_EQ(shape_of("vfe.pfn_layers.0.linear.weight"), (Shape{64, 10}));
  EXPECT_EQ(shape_of("vfe.pfn_layers.0.norm.running_var"), (Shape{64}));
  EXPECT_EQ(shape_of("segmentation_head.down1.maxpool_conv.1.double_conv.0.weight"), (Shape{128, 64, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.down1.maxpool_conv.1.double_conv.4.bias"), (Shape{128}));
  EXPECT_EQ(shape_of("segmentation_head.down4.maxpool_conv.1.double_conv.3.weight"), (Shape{512, 512, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.up1.conv.double_conv.0.weight"), (Shape{512, 1024, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.up1.conv.double_conv.3.weight"), (Shape{256, 512, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.up4.conv.double_conv.0.weight"), (Shape{64, 128, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.up4.conv.double_conv.3.weight"), (Shape{64, 64, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.outc.conv.weight"), (Shape{12, 64, 1, 1}));
  EXPECT_EQ(ps.counters().count("segmentation_head.up2.conv.double_conv.1.num_batches_tracked"), 1u);
  // The authors' U-Net (milesial's, without its input block) built in PyTorch with
  // n_channels 64, 12 classes, bilinear: sum(p.numel()) = 17,229,132. Plus the PFN's 640 + 128.
  int64_t unet = 0;
  for (const ParamEntry& e : ps.entries())
    if (e.trainable && e.name.rfind("segmentation_head.", 0) == 0) unet += shape_numel(e.shape);
  EXPECT_EQ(unet, 17229132);
  EXPECT_EQ(ps.num_trainable(), unet + 640 + 128);
}

TEST(Model, TransposedVariantWidths) {
  ModelConfig c = tiny_config(OccupancyInput::Occupancy3D, /*transposed=*/true);
  c.base_width = 8;
  c.depth = 4;
  c.grid.x_max = 3.2, c.grid.y_max = 1.6;
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend);
  const ParameterSet& ps = net.parameters();
  const auto shape_of = [&](const std::string& name) { return ps.entries()[static_cast<size_t>(ps.find(name))].shape; };
  // I = C + Q = 7; widths 2b, 4b, 8b, 16b = 16, 32, 64, 128.
  EXPECT_EQ(shape_of("occupancy.conv.weight"), (Shape{3, 4, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.down1.maxpool_conv.1.double_conv.0.weight"), (Shape{16, 7, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.down4.maxpool_conv.1.double_conv.3.weight"), (Shape{128, 128, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.up1.up.weight"), (Shape{128, 64, 2, 2}));
  EXPECT_EQ(shape_of("segmentation_head.up1.conv.double_conv.0.weight"), (Shape{64, 128, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.up4.up.weight"), (Shape{16, 8, 2, 2}));
  EXPECT_EQ(shape_of("segmentation_head.up4.conv.double_conv.0.weight"), (Shape{8, 15, 3, 3}));
  EXPECT_EQ(shape_of("segmentation_head.up4.conv.double_conv.3.weight"), (Shape{8, 8, 3, 3}));
}

// Finite differences of the whole model (training-mode forward and loss) against the
// backward's gradient, for every input variant: one random direction per parameter tensor, so
// that a wrong gradient is pinned to its layer. The model runs in float, and ReLU and max-pool
// kinks lie within any usable step of some of its thousands of activations, so agreement is
// to about 10% here, or a few percent of the gradient's norm (measured: the difference
// shrinks steadily as the step does). A wiring
// error (a missing path, a wrong skip connection, a sign) is off by far more; each op's
// backward is checked exactly, in double, in the test_host_* files.
class ModelGradient : public ::testing::TestWithParam<int> {};

TEST_P(ModelGradient, MatchesFiniteDifferences) {
  const int variant = GetParam();
  const ModelConfig c = variant == 0   ? tiny_config()
                        : variant == 1 ? tiny_config(OccupancyInput::Observability2D)
                        : variant == 2 ? tiny_config(OccupancyInput::Occupancy3D, true)
                                       : tiny_config(OccupancyInput::None, false, /*grid_map=*/true);
  // The reference backend: float central differences need the reference's smaller rounding
  // (the fast paths are checked against it below).
  auto backend = make_cpu_reference_backend();
  PillarSegNet net(c, *backend, /*seed=*/11);
  const TinyData data = tiny_data(c, 2, 5);
  ParameterSet& ps = net.parameters();
  const std::vector<float> theta = ps.download_flat(ps.values());
  const std::vector<float> buffers = ps.download_flat(ps.buffers());
  const auto loss_at = [&](const std::vector<float>& values, LossKind kind) {
    ps.upload_flat(ps.values(), values);
    ps.upload_flat(ps.buffers(), buffers);
    net.forward(data.batch, true);
    return net.loss(data.labels, kind, kCoefficients);
  };
  Rng rng(3);
  for (LossKind kind : {LossKind::CrossEntropy, LossKind::Bce}) {
    loss_at(theta, kind);
    net.backward();
    const std::vector<float> grad = ps.download_flat(ps.grads());
    int checked = 0;
    for (const ParamEntry& e : ps.entries()) {
      if (!e.trainable) continue;
      const int64_t n = shape_numel(e.shape);
      std::vector<float> plus(theta), minus(theta);
      double analytic = 0, norm_sq = 0;
      const double eps = 1e-4;
      for (int64_t i = 0; i < n; ++i) {
        const size_t k = static_cast<size_t>(e.offset + i);
        const double d = rng.normal();
        analytic += grad[k] * d;
        norm_sq += double{grad[k]} * grad[k];
        plus[k] = static_cast<float>(theta[k] + eps * d);
        minus[k] = static_cast<float>(theta[k] - eps * d);
      }
      const double numeric = (loss_at(plus, kind) - loss_at(minus, kind)) / (2 * eps);
      // The directional derivative along N(0, I) has spread |g|: a wrong gradient misses by
      // about that much, kinks by a few percent of it.
      EXPECT_NEAR(numeric, analytic, 0.1 * std::abs(analytic) + 0.05 * std::sqrt(norm_sq) + 1e-3)
          << e.name << " (variant " << variant << ", " << (kind == LossKind::Bce ? "bce" : "ce") << ")";
      ++checked;
    }
    EXPECT_GT(checked, 20);
  }
}

INSTANTIATE_TEST_SUITE_P(Variants, ModelGradient, ::testing::Values(0, 1, 2, 3));

TEST(Model, AdamStepsReduceTheLossAndEvalUsesRunningStatistics) {
  const ModelConfig c = tiny_config(OccupancyInput::Observability2D);
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend, 1);
  const TinyData data = tiny_data(c, 2, 9);
  ParameterSet& ps = net.parameters();
  double first = 0, last = 0;
  for (int step = 1; step <= 30; ++step) {
    net.forward(data.batch, true);
    const double loss = net.loss(data.labels, LossKind::CrossEntropy, kCoefficients);
    if (step == 1) first = loss;
    last = loss;
    net.backward();
    AdamOptions adam;
    adam.lr = 1e-2;
    adam.beta2 = 0.99;
    Ref values = ps.values(), m = ps.adam_m(), v = ps.adam_v();
    backend->adam_step(values, ps.grads(), m, v, step, adam);
  }
  EXPECT_LT(last, 0.7 * first);
  EXPECT_EQ(ps.counters().at("segmentation_head.down1.maxpool_conv.1.double_conv.1.num_batches_tracked"), 30);
  // Eval mode is deterministic and differs from training mode (running vs batch statistics).
  net.forward(data.batch, false);
  const Tensor<float> eval1 = net.download_logits();
  net.forward(data.batch, false);
  EXPECT_EQ(eval1, net.download_logits());
  net.forward(data.batch, true);
  EXPECT_FALSE(eval1 == net.download_logits());
  const Tensor<uint8_t> labels = net.predict_labels();
  for (uint8_t l : labels) {
    EXPECT_GE(l, 1);
    EXPECT_LE(l, 12);
  }
}

// Precise BatchNorm: momentum 1 and then 1/2 over two batches leaves each running statistic at the
// mean of the two batches' statistics; momentum 0 restores the module's own update rule.
TEST(Model, BatchNormMomentumOverrideAveragesBatches) {
  const ModelConfig c = tiny_config(OccupancyInput::Observability2D);
  const TinyData first = tiny_data(c, 2, 21), second = tiny_data(c, 2, 22);
  auto backend = make_cpu_backend();
  const auto running_after = [&](const std::vector<std::pair<const TinyData*, float>>& forwards) {
    PillarSegNet net(c, *backend, 5);
    for (const auto& [data, momentum] : forwards) {
      net.set_batchnorm_momentum(momentum);
      net.forward(data->batch, true);
    }
    const ParameterSet& ps = net.parameters();
    std::map<std::string, std::vector<float>> stats;
    for (const char* name : {"vfe.pfn_layers.0.norm.running_mean", "occupancy.norm.running_var",
                             "segmentation_head.up2.conv.double_conv.4.running_mean"}) {
      const Tensor<float> t = ps.download(ps.find(name));
      EXPECT_GT(t.numel(), 0) << name;
      stats[name].assign(t.begin(), t.end());
    }
    return stats;
  };
  const auto alone1 = running_after({{&first, 1.0f}}), alone2 = running_after({{&second, 1.0f}});
  const auto averaged = running_after({{&first, 1.0f}, {&second, 0.5f}});
  for (const auto& [name, values] : averaged) {
    ASSERT_EQ(values.size(), alone1.at(name).size());
    for (size_t i = 0; i < values.size(); ++i) {
      const float expected = 0.5f * (alone1.at(name)[i] + alone2.at(name)[i]);
      EXPECT_NEAR(values[i], expected, 1e-5f * (1 + std::abs(expected))) << name << "[" << i << "]";
    }
  }
  // Restored: the PFN's momentum 0.01 after a momentum-1 batch.
  const auto restored = running_after({{&first, 1.0f}, {&second, 0.0f}});
  const std::string pfn = "vfe.pfn_layers.0.norm.running_mean";
  for (size_t i = 0; i < restored.at(pfn).size(); ++i) {
    const float expected = 0.99f * alone1.at(pfn)[i] + 0.01f * alone2.at(pfn)[i];
    EXPECT_NEAR(restored.at(pfn)[i], expected, 1e-5f * (1 + std::abs(expected)));
  }
  PillarSegNet net(c, *backend, 5);
  EXPECT_THROW(net.set_batchnorm_momentum(1.5f), Error);
}

TEST(Model, EmptyScanAndBadInputs) {
  const ModelConfig c = tiny_config();
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend);
  ModelBatch empty;
  empty.batch = 1;
  net.forward(empty, false);  // no pillars: an all-zero canvas still gives a prediction
  EXPECT_EQ(net.predict_labels().shape(), (Shape{1, 16, 24}));
  ModelBatch bad = tiny_data(c, 1, 2).batch;
  bad.pillar_points.reshape({bad.pillar_points.dim(0), 1, 30});
  EXPECT_THROW(net.forward(bad, false), Error);
  const ModelConfig occ = tiny_config(OccupancyInput::Observability2D);
  PillarSegNet with_occupancy(occ, *backend);
  EXPECT_THROW(with_occupancy.forward(tiny_data(c, 1, 2).batch, false), Error);  // no occupancy input given
}

// The fast CPU backend against the reference one on the same weights, random running
// statistics and inputs: the eval forward (fused Conv -> BN -> ReLU, memory overlaid by
// lifetime) and a training step's gradients; odd grid sizes and batch 1 and 2.
class FastBackend : public ::testing::TestWithParam<std::tuple<int, int>> {};

TEST_P(FastBackend, MatchesReferenceBackend) {
  const auto [variant, B] = GetParam();
  ModelConfig c = variant == 0   ? tiny_config()
                  : variant == 1 ? tiny_config(OccupancyInput::Observability2D)
                  : variant == 2 ? tiny_config(OccupancyInput::Occupancy3D, true)
                                 : tiny_config(OccupancyInput::None, false, /*grid_map=*/true);
  if (variant == 1) c.grid.x_max = 2.3, c.grid.y_max = 1.5;  // 23 x 15 cells: odd sizes at every level
  const TinyData data = tiny_data(c, B, 40 + variant);
  auto fast_backend = make_cpu_backend();
  auto reference_backend = make_cpu_reference_backend();
  PillarSegNet fast(c, *fast_backend, 3), reference(c, *reference_backend, 3);
  // Running statistics away from (0, 1), so that the folded BatchNorm is exercised, and means
  // small against the activations, so that the ReLUs do not silence the network (which would
  // make every eval logit the head's bias, whatever the path).
  Rng rng(17);
  for (PillarSegNet* net : {&fast, &reference}) {
    ParameterSet& ps = net->parameters();
    Rng same = rng;
    for (size_t i = 0; i < ps.entries().size(); ++i) {
      const ParamEntry& e = ps.entries()[i];
      if (e.trainable) continue;
      Tensor<float> t = ps.download(static_cast<int>(i));
      const bool mean = e.name.find("running_mean") != std::string::npos;
      for (float& v : t) v = static_cast<float>(mean ? same.uniform(-0.05, 0.05) : same.uniform(0.5, 1.5));
      ps.upload(static_cast<int>(i), t);
    }
  }

  for (int pass = 0; pass < 2; ++pass) {  // eval, then eval again after a training step
    fast.forward(data.batch, false);
    reference.forward(data.batch, false);
    const Tensor<float> eval_logits = reference.download_logits();
    EXPECT_TRUE(test::all_close(fast.download_logits(), eval_logits, 1e-4, 1e-3)) << "eval logits, pass " << pass;
    // The comparison has teeth: the eval logits depend on the input (they differ between cells).
    EXPECT_GT(*std::max_element(eval_logits.begin(), eval_logits.end()) -
                  *std::min_element(eval_logits.begin(), eval_logits.end()),
              1e-3)
        << "pass " << pass;
    EXPECT_LT(fast.activation_bytes(), reference.activation_bytes() + 1);

    fast.forward(data.batch, true);
    reference.forward(data.batch, true);
    EXPECT_TRUE(test::all_close(fast.download_logits(), reference.download_logits(), 1e-4, 1e-3))
        << "training logits, pass " << pass;
    fast.loss(data.labels, LossKind::CrossEntropy, kCoefficients);
    reference.loss(data.labels, LossKind::CrossEntropy, kCoefficients);
    fast.backward();
    reference.backward();
    const std::vector<float> g_fast = fast.parameters().download_flat(fast.parameters().grads());
    const std::vector<float> g_ref = reference.parameters().download_flat(reference.parameters().grads());
    double scale = 0;
    for (float g : g_ref) scale = std::max(scale, double{std::abs(g)});
    EXPECT_TRUE(test::all_close(g_fast.data(), g_ref.data(), static_cast<int64_t>(g_ref.size()), 1e-4 * scale, 1e-3))
        << "gradients, pass " << pass;
  }
}

INSTANTIATE_TEST_SUITE_P(VariantsAndBatches, FastBackend,
                         ::testing::Combine(::testing::Values(0, 1, 2, 3), ::testing::Values(1, 2)));

// Eval overlays activations by lifetime: less memory than training (which keeps what the
// backward reads, and the gradients), and the same logits after switching modes back and forth.
TEST(Model, EvalMemoryIsPlannedByLifetime) {
  ModelConfig c = tiny_config();
  c.depth = 3;
  c.grid.x_max = 6.4, c.grid.y_max = 3.2;  // 64 x 32 cells
  const TinyData data = tiny_data(c, 1, 8);
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend, 2);
  ParameterSet& ps = net.parameters();
  const std::vector<float> running = ps.download_flat(ps.buffers());
  net.forward(data.batch, false);
  const size_t eval_bytes = net.activation_bytes();  // both include the pillar buffers
  const Tensor<float> first = net.download_logits();
  net.forward(data.batch, true);
  const size_t training_bytes = net.activation_bytes();
  EXPECT_LT(eval_bytes, training_bytes);
  ps.upload_flat(ps.buffers(), running);  // undo the training forward's running-statistic update
  net.forward(data.batch, false);
  EXPECT_EQ(net.activation_bytes(), eval_bytes);
  EXPECT_EQ(first, net.download_logits());
  EXPECT_THROW(net.backward(), Error);
}

// Inference holds only the parameter values and the BatchNorm buffers: the gradients appear
// with the first backward (zero-filled before it writes them), the Adam moments with the first
// optimiser step (zero-filled), each once.
TEST(Model, GradientsAndAdamMomentsAreAllocatedOnFirstUse) {
  const ModelConfig c = tiny_config(OccupancyInput::Observability2D, /*transposed=*/true);
  const TinyData data = tiny_data(c, 1, 12);
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend, 4);
  ParameterSet& ps = net.parameters();
  const auto padded_bytes = [](int64_t n) { return static_cast<size_t>((n + 15) / 16 * 16) * sizeof(float); };
  const size_t values_and_buffers = padded_bytes(ps.num_trainable()) + padded_bytes(ps.num_buffer_values());
  const size_t one_section = padded_bytes(ps.num_trainable());

  net.forward(data.batch, false);
  net.predict_labels();
  EXPECT_EQ(ps.allocated_bytes(), values_and_buffers);
  EXPECT_FALSE(ps.has_gradients());
  EXPECT_FALSE(ps.has_optimizer_state());
  // A checkpoint's moments before any step: zeros, without allocating them.
  EXPECT_EQ(ps.download_adam_m(), std::vector<float>(static_cast<size_t>(ps.num_trainable()), 0.0f));
  EXPECT_EQ(ps.download_adam_v(), std::vector<float>(static_cast<size_t>(ps.num_trainable()), 0.0f));
  EXPECT_FALSE(ps.has_optimizer_state());

  const std::vector<float> zeros(static_cast<size_t>(ps.num_trainable()), 0.0f);
  EXPECT_EQ(ps.download_flat(ps.grads()), zeros);
  EXPECT_EQ(ps.allocated_bytes(), values_and_buffers + one_section);
  net.forward(data.batch, true);
  net.loss(data.labels, LossKind::CrossEntropy, kCoefficients);
  net.backward();
  const std::vector<float> grads = ps.download_flat(ps.grads());
  EXPECT_NE(grads, zeros);
  EXPECT_EQ(ps.allocated_bytes(), values_and_buffers + one_section);
  EXPECT_FALSE(ps.has_optimizer_state());

  EXPECT_EQ(ps.download_flat(ps.adam_m()), zeros);
  EXPECT_EQ(ps.download_flat(ps.adam_v()), zeros);
  EXPECT_TRUE(ps.has_optimizer_state());
  EXPECT_EQ(ps.allocated_bytes(), values_and_buffers + 3 * one_section);
  Ref values = ps.values(), m = ps.adam_m(), v = ps.adam_v();
  backend->adam_step(values, ps.grads(), m, v, 1, AdamOptions{});
  EXPECT_NE(ps.download_adam_m(), zeros);
  EXPECT_EQ(ps.download_adam_m(), ps.download_flat(ps.adam_m()));
  EXPECT_EQ(ps.allocated_bytes(), values_and_buffers + 3 * one_section);
  ps.zero_grads();
  EXPECT_EQ(ps.download_flat(ps.grads()), zeros);
}

// The training plan overlays activations and gradients by lifetime: a second step on the same
// batch and weights (after an eval forward in between) repeats the first bit for bit, whatever
// the earlier step left in the shared bytes; a backward without a fresh loss() is refused.
TEST(Model, TrainingMemoryIsPlannedByLifetime) {
  for (int variant = 0; variant < 2; ++variant) {
    SCOPED_TRACE(variant);
    ModelConfig c = variant == 0 ? tiny_config(OccupancyInput::Observability2D)
                                 : tiny_config(OccupancyInput::Occupancy3D, /*transposed=*/true, /*grid_map=*/true);
    c.grid.x_max = 2.3, c.grid.y_max = 1.5;  // 23 x 15 cells: odd sizes at every level
    const TinyData data = tiny_data(c, 2, 70 + variant), other = tiny_data(c, 2, 80 + variant);
    auto backend = make_cpu_backend();
    PillarSegNet net(c, *backend, 6);
    ParameterSet& ps = net.parameters();
    const auto step = [&](const TinyData& d) {
      net.forward(d.batch, true);
      const double loss = net.loss(d.labels, LossKind::CrossEntropy, kCoefficients);
      net.backward();
      return std::make_tuple(loss, net.download_logits(), ps.download_flat(ps.grads()));
    };
    const auto first = step(data);
    const size_t training_bytes = net.activation_bytes();
    EXPECT_THROW(net.backward(), Error);
    step(other);  // different values through the same bytes
    net.forward(other.batch, false);
    const auto again = step(data);
    EXPECT_EQ(std::get<0>(again), std::get<0>(first));
    EXPECT_EQ(std::get<1>(again), std::get<1>(first));
    EXPECT_EQ(std::get<2>(again), std::get<2>(first));
    EXPECT_EQ(net.activation_bytes(), training_bytes);
  }
}
