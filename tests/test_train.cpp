// Training end to end on a tiny simulated data set: checkpoints and the metrics log, bitwise
// reproducibility, exact resume, the stop on a non-finite loss, and evaluation.
#include <gtest/gtest.h>

#include <unistd.h>

#include <fstream>

#include "core/io.hpp"
#include "core/parallel.hpp"
#include "engine/cuda/cuda_backend.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/eval/evaluate.hpp"
#include "engine/pipeline/scan_inputs.hpp"
#include "engine/sim/simulate.hpp"
#include "engine/train/checkpoint.hpp"
#include "engine/train/trainer.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
namespace fs = std::filesystem;

namespace {

// 3 scans of sequence 00 and 2 of sequence 08, written once per process.
const fs::path& tiny_data() {
  static const fs::path root = [] {
    const fs::path dir =
        fs::path(PILLARSEG_BINARY_DIR) / "test_tmp" / ("TrainData." + std::to_string(::getpid()));
    fs::remove_all(dir);
    sim::SimulateOptions o;
    o.out = dir;
    o.sequences = 1;
    o.scans = 3;
    o.seed = 7;
    o.points_per_scan = 30000;
    sim::simulate(o);
    o.first_sequence = 8;
    o.scans = 2;
    sim::simulate(o);
    return dir;
  }();
  return root;
}

std::string tiny_config_text(const std::string& extra_train = "") {
  return R"(grid: {x: [-6.4, 6.4], y: [-3.2, 3.2], z: [-2.5, 1.5], cell: 0.2, voxel_z: 0.5}
model: {max_points_per_pillar: 8, pillar_channels: 4, occupancy: 2d, occupancy_channels: 2, base_width: 4, depth: 2}
train:
  epochs: 2
  batch_size: 2
  seed: 3
  sequences: [0]
  optimizer: {lr: 0.01}
)" + extra_train +
         "eval: {sequences: [8]}\n";
}

TrainOptions options_for(const fs::path& run_dir, const std::string& config_text) {
  TrainOptions o;
  o.data_root = tiny_data();
  o.run_dir = run_dir;
  o.config = parse_run_config(config_text, "test config");
  o.cache_dir = run_dir / "cache";
  o.progress = false;
  return o;
}

std::vector<float> checkpoint_values(const fs::path& path) {
  const Checkpoint c = read_checkpoint(path);
  std::vector<float> all;
  for (const std::string& name : c.file.names()) {
    if (c.file.at(name).dtype != weights::DType::F32) continue;
    const Tensor<float> t = c.file.get_f32(name);
    all.insert(all.end(), t.begin(), t.end());
  }
  return all;
}

}  // namespace

// Taking one scan's tensors gives the batch that copying them does; the scan keeps its
// observability.
TEST(Collate, OneScanTakenEqualsOneScanCopied) {
  ModelConfig model = parse_run_config(tiny_config_text(), "test config").model;
  model.grid_map_input = true;
  const Scan scan = read_scan(tiny_data() / "sequences" / "00" / "velodyne" / "000001.bin");
  const ScanInputs inputs = compute_scan_inputs(scan.points, Eigen::Vector3d::Zero(), model,
                                                host::SampleMode::Inference, nullptr, true);
  ASSERT_GT(inputs.pillar_cells.dim(0), 0);
  const ModelBatch copied = collate({&inputs}, model);
  ScanInputs moved = inputs;
  const ModelBatch taken = collate(std::move(moved), model);
  EXPECT_EQ(taken.batch, 1);
  EXPECT_EQ(taken.pillar_points, copied.pillar_points);
  EXPECT_EQ(taken.pillar_cells, copied.pillar_cells);
  EXPECT_EQ(taken.occupancy, copied.occupancy);
  EXPECT_EQ(taken.grid_map, copied.grid_map);
  EXPECT_EQ(moved.observability, inputs.observability);
  // A map of the wrong size is refused, naming what was expected.
  ScanInputs bad = inputs;
  bad.grid_map = Tensor<float>({3, 2, 2});
  EXPECT_THROW(collate(std::move(bad), model), Error);
}

TEST(Train, WritesCheckpointAndLogAndIsBitwiseReproducible) {
  const fs::path dir = test::temp_dir();
  const TrainResult a = train(options_for(dir / "a", tiny_config_text()));
  EXPECT_EQ(a.epochs_done, 2);
  EXPECT_EQ(a.steps_done, 4);  // 3 scans, batch 2: 2 steps an epoch
  ASSERT_TRUE(fs::exists(dir / "a" / "checkpoint.safetensors"));
  const std::string log = read_file_text(dir / "a" / "metrics.jsonl");
  EXPECT_EQ(std::count(log.begin(), log.end(), '\n'), 4 + 2);  // a line per step and per epoch
  EXPECT_NE(log.find(R"("type": "epoch", "epoch": 2)"), std::string::npos) << log;
  const Checkpoint c = read_checkpoint(dir / "a" / "checkpoint.safetensors");
  EXPECT_EQ(c.state.epoch, 2);
  EXPECT_EQ(c.state.step, 4);
  EXPECT_TRUE(c.has_optimizer);
  ASSERT_TRUE(c.config.has_value());
  EXPECT_EQ(c.config->model.base_width, 4);
  EXPECT_EQ(c.file.get_i64("vfe.pfn_layers.0.norm.num_batches_tracked"), std::vector<int64_t>{4});

  train(options_for(dir / "b", tiny_config_text()));
  EXPECT_EQ(checkpoint_values(dir / "a" / "checkpoint.safetensors"),
            checkpoint_values(dir / "b" / "checkpoint.safetensors"));
  // Another seed trains another model.
  std::string other = tiny_config_text();
  other.replace(other.find("seed: 3"), 7, "seed: 4");
  train(options_for(dir / "c", other));
  EXPECT_NE(checkpoint_values(dir / "a" / "checkpoint.safetensors"),
            checkpoint_values(dir / "c" / "checkpoint.safetensors"));
}

TEST(Train, ResumeIsExact) {
  const fs::path dir = test::temp_dir();
  // With precise BatchNorm too: the recalibrated statistics are part of the checkpoint.
  for (const std::string extra : {"", "  precise_bn_batches: 1\n"}) {
    const std::string name = extra.empty() ? "" : "_precise_bn";
    train(options_for(dir / ("straight" + name), tiny_config_text(extra)));
    TrainOptions first = options_for(dir / ("split" + name), tiny_config_text(extra));
    first.max_epochs_this_run = 1;
    EXPECT_EQ(train(first).epochs_done, 1);
    TrainOptions second = options_for(dir / ("split" + name), tiny_config_text(extra));
    second.resume = true;
    EXPECT_EQ(train(second).epochs_done, 2);
    EXPECT_EQ(checkpoint_values(dir / ("straight" + name) / "checkpoint.safetensors"),
              checkpoint_values(dir / ("split" + name) / "checkpoint.safetensors"));
  }
  // Recalibration changes the running statistics, and only them.
  const Checkpoint plain = read_checkpoint(dir / "straight" / "checkpoint.safetensors");
  const Checkpoint precise =
      read_checkpoint(dir / "straight_precise_bn" / "checkpoint.safetensors");
  EXPECT_EQ(plain.file.get_f32("segmentation_head.outc.conv.weight"),
            precise.file.get_f32("segmentation_head.outc.conv.weight"));
  EXPECT_FALSE(plain.file.get_f32("vfe.pfn_layers.0.norm.running_mean") ==
               precise.file.get_f32("vfe.pfn_layers.0.norm.running_mean"));
  // A fresh run refuses to overwrite, and resume refuses another config.
  EXPECT_THROW(train(options_for(dir / "split", tiny_config_text())), Error);
  std::string other = tiny_config_text();
  other.replace(other.find("batch_size: 2"), 13, "batch_size: 1");
  TrainOptions changed = options_for(dir / "split", other);
  changed.resume = true;
  EXPECT_THROW(train(changed), Error);
}

TEST(Train, NonFiniteLossStopsAndKeepsTheLastGoodCheckpoint) {
  const fs::path dir = test::temp_dir();
  // One scan, batch 1: one step an epoch. A huge constant rate makes the weights overflow in
  // the first step, so epoch 2's loss is not finite.
  std::string text = tiny_config_text();
  text.replace(text.find("optimizer: {lr: 0.01}"), 21,
               "optimizer: {lr: 1.0e+30, schedule: constant, grad_clip: 0}");
  text.replace(text.find("batch_size: 2"), 13, "batch_size: 1");
  text.replace(text.find("sequences: [0]"), 14, "sequences: [0]\n  max_scans_per_sequence: 1");
  try {
    train(options_for(dir / "nan", text));
    FAIL() << "expected a non-finite loss error";
  } catch (const Error& e) {
    const std::string msg = e.what();
    EXPECT_NE(msg.find("non-finite"), std::string::npos) << msg;
    EXPECT_NE(msg.find("checkpoint.safetensors"), std::string::npos) << msg;
  }
  const Checkpoint c = read_checkpoint(dir / "nan" / "checkpoint.safetensors");
  EXPECT_EQ(c.state.epoch, 1);
}

TEST(Train, EvaluateTrainedCheckpointBothModes) {
  const fs::path dir = test::temp_dir();
  const TrainResult r = train(options_for(dir / "run", tiny_config_text()));
  const Checkpoint ckpt = read_checkpoint(r.checkpoint);
  const RunConfig config = config_for(ckpt, "");
  ScanSegmenter cpu(config.model, make_cpu_backend());
  load_weights(ckpt, cpu.net(), false);
  EvalOptions o;
  o.data_root = tiny_data();
  o.cache_dir = dir / "cache";
  o.progress = false;
  const SegmentationMetrics sparse = evaluate(cpu, config, o);
  // The device pipeline (the CUDA backend on the emulation) from the raw points: the same labelled
  // cells, and nearly every prediction the same (the backends' float sums differ in the last bits).
  ScanSegmenter emu(config.model, std::make_unique<CudaBackend>());
  load_weights(ckpt, emu.net(), false);
  const SegmentationMetrics on_device = evaluate(emu, config, o);
  EXPECT_EQ(on_device.labelled_cells(), sparse.labelled_cells());
  EXPECT_NEAR(on_device.miou(), sparse.miou(), 0.01);
  o.mode = GroundTruthKind::dense;
  const SegmentationMetrics dense = evaluate(cpu, config, o);
  EXPECT_GT(sparse.labelled_cells(), 0);
  // Dense ground truth labels more cells than one sweep does.
  EXPECT_GT(dense.labelled_cells(), sparse.labelled_cells());
  EXPECT_GE(sparse.miou(), 0.0);
  EXPECT_LE(sparse.miou(), 1.0);
  EXPECT_EQ(method_label(config.model), "Pillar + 2D Occupancy");
  // A weights-only file (no config): the architecture from its tensor shapes, on the paper's grid.
  weights::SafeTensors bare;
  for (const std::string& name : ckpt.file.names())
    if (name.rfind("optimizer.", 0) != 0) bare.add(ckpt.file.at(name));
  bare.write(dir / "bare.safetensors");
  const RunConfig inferred = config_for(read_checkpoint(dir / "bare.safetensors"), "");
  EXPECT_EQ(inferred.model.grid, GridSpec{});
  EXPECT_EQ(inferred.model.pillar_channels, config.model.pillar_channels);
  EXPECT_EQ(inferred.model.occupancy, config.model.occupancy);
  EXPECT_EQ(inferred.model.occupancy_channels, config.model.occupancy_channels);
  EXPECT_EQ(inferred.model.base_width, config.model.base_width);
  EXPECT_EQ(inferred.model.depth, config.model.depth);
  EXPECT_EQ(inferred.model.transposed, config.model.transposed);
  EXPECT_EQ(inferred.model.grid_map_input, config.model.grid_map_input);
}
