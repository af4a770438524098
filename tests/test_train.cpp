// Training end to end on a tiny simulated data set: checkpoints and the metrics log, bitwise
// reproducibility, exact resume, the stop on a non-finite loss, and evaluation.
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <fstream>
#include <map>
#include <sstream>
#include <thread>

#include "core/io.hpp"
#include "core/parallel.hpp"
#include "engine/cuda/cuda_backend.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/eval/evaluate.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/pipeline/scan_inputs.hpp"
#include "engine/sim/simulate.hpp"
#include "engine/train/prefetcher.hpp"
#include "engine/train/trainer.hpp"
#include "engine/util/tensorboard.hpp"
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

// The model's F32 tensors of a checkpoint (without the optimiser's moments).
std::vector<float> model_values(const Checkpoint& c) {
  std::vector<float> all;
  for (const std::string& name : c.file.names()) {
    if (name.rfind("optimizer.", 0) == 0 || c.file.at(name).dtype != weights::DType::F32) continue;
    const Tensor<float> t = c.file.get_f32(name);
    all.insert(all.end(), t.begin(), t.end());
  }
  return all;
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

// The checkpoint's num_batches_tracked counters, name by name.
std::map<std::string, int64_t> checkpoint_counters(const fs::path& path) {
  const Checkpoint c = read_checkpoint(path);
  std::map<std::string, int64_t> counters;
  for (const std::string& name : c.file.names())
    if (name.find("num_batches_tracked") != std::string::npos)
      counters[name] = c.file.get_i64(name).at(0);
  return counters;
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
  // With precise BatchNorm too: the recalibrated statistics are part of the checkpoint. The
  // straight run recalibrates after epoch 2 only, the split one after each of its runs: the
  // statistics of epoch 1's end are overwritten unread.
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
  // num_batches_tracked counts the training batches, not the recalibration's forwards.
  const std::map<std::string, int64_t> counted =
      checkpoint_counters(dir / "straight" / "checkpoint.safetensors");
  ASSERT_FALSE(counted.empty());
  EXPECT_GT(counted.begin()->second, 0);
  EXPECT_EQ(checkpoint_counters(dir / "straight_precise_bn" / "checkpoint.safetensors"), counted);
  EXPECT_EQ(checkpoint_counters(dir / "split_precise_bn" / "checkpoint.safetensors"), counted);
  // A fresh run refuses to overwrite, and resume refuses another config.
  EXPECT_THROW(train(options_for(dir / "split", tiny_config_text())), Error);
  std::string other = tiny_config_text();
  other.replace(other.find("batch_size: 2"), 13, "batch_size: 1");
  TrainOptions changed = options_for(dir / "split", other);
  changed.resume = true;
  EXPECT_THROW(train(changed), Error);
}

// train.average_epochs: the final weights are the mean of the last K epochs' weights (the
// training itself unchanged), the BatchNorm statistics estimated again for them, and a run
// resumed inside the averaging window ends with the same bits.
TEST(Train, AveragesTheLastEpochsWeights) {
  const fs::path dir = test::temp_dir();
  const auto with = [](const std::string& extra) {
    std::string text = tiny_config_text("  precise_bn_batches: 1\n" + extra);
    text.replace(text.find("epochs: 2"), 9, "epochs: 3");
    return text;
  };
  // Without averaging, epoch by epoch: the weights after epochs 2 and 3.
  std::vector<std::map<std::string, Tensor<float>>> plain;
  for (int epoch = 1; epoch <= 3; ++epoch) {
    TrainOptions o = options_for(dir / "plain", with(""));
    o.max_epochs_this_run = 1;
    o.resume = epoch > 1;
    train(o);
    const Checkpoint c = read_checkpoint(dir / "plain" / "checkpoint.safetensors");
    EXPECT_EQ(c.file.contains(kAverageSumName), false);
    std::map<std::string, Tensor<float>> tensors;
    for (const std::string& name : c.file.names())
      if (c.file.at(name).dtype == weights::DType::F32) tensors.emplace(name, c.file.get_f32(name));
    plain.push_back(std::move(tensors));
  }
  train(options_for(dir / "averaged", with("  average_epochs: 2\n")));
  const Checkpoint averaged = read_checkpoint(dir / "averaged" / "checkpoint.safetensors");
  EXPECT_FALSE(averaged.file.contains(kAverageSumName)) << "the finished run drops the sum";
  int trainable = 0, statistics = 0, moved = 0;
  for (const std::string& name : averaged.file.names()) {
    if (name.rfind("optimizer.", 0) == 0 || averaged.file.at(name).dtype != weights::DType::F32)
      continue;
    const Tensor<float> got = averaged.file.get_f32(name);
    const Tensor<float>&w2 = plain[1].at(name), &w3 = plain[2].at(name);
    if (name.find("running_") != std::string::npos) {
      // Estimated again under the averaged weights: not the last epoch's statistics.
      ++statistics;
      moved += !(got == w3);
      continue;
    }
    ++trainable;
    ASSERT_EQ(got.numel(), w3.numel()) << name;
    for (int64_t i = 0; i < got.numel(); ++i)
      ASSERT_EQ(got[i], (w2[i] + w3[i]) / 2.0f) << name << "[" << i << "]";
  }
  EXPECT_GT(trainable, 20);
  EXPECT_GT(statistics, 4);
  EXPECT_GT(moved, statistics / 2);
  // The weights did move between the two epochs (an average of equal weights proves nothing).
  EXPECT_FALSE(plain[1].at("segmentation_head.outc.conv.weight") ==
               plain[2].at("segmentation_head.outc.conv.weight"));
  // Resumed after epoch 2, inside the window: the checkpoint carries the sum, and the run ends
  // with the straight run's bits.
  TrainOptions first = options_for(dir / "split", with("  average_epochs: 2\n"));
  first.max_epochs_this_run = 2;
  train(first);
  const Checkpoint mid = read_checkpoint(dir / "split" / "checkpoint.safetensors");
  ASSERT_TRUE(mid.file.contains(kAverageSumName));
  // After epoch 2 the sum is epoch 2's weights (compared as sorted multisets: the sum is in the
  // parameter set's flat order, the file in the names' order).
  const Tensor<float> sum = mid.file.get_f32(kAverageSumName);
  std::vector<float> sum_sorted(sum.begin(), sum.end()), epoch2;
  for (const auto& [name, t] : plain[1])
    if (name.rfind("optimizer.", 0) != 0 && name.find("running_") == std::string::npos)
      epoch2.insert(epoch2.end(), t.begin(), t.end());
  std::sort(sum_sorted.begin(), sum_sorted.end());
  std::sort(epoch2.begin(), epoch2.end());
  EXPECT_EQ(sum_sorted, epoch2);
  TrainOptions second = options_for(dir / "split", with("  average_epochs: 2\n"));
  second.resume = true;
  train(second);
  EXPECT_EQ(checkpoint_values(dir / "averaged" / "checkpoint.safetensors"),
            checkpoint_values(dir / "split" / "checkpoint.safetensors"));
}

// The step lines of a metrics log without their wall-clock field.
std::vector<std::string> step_lines(const fs::path& log_path) {
  std::vector<std::string> out;
  std::istringstream in(read_file_text(log_path));
  for (std::string line; std::getline(in, line);) {
    if (line.find(R"("type": "step")") == std::string::npos) continue;
    out.push_back(line.substr(0, line.find(R"(, "elapsed_s")")));
  }
  return out;
}

// What resume keeps of a metrics log (the checkpoint of epoch 1, step 2): the lines up to it,
// a later epoch's or step's dropped, a last line cut short by a kill dropped, a number too long
// for int64 read as beyond any checkpoint; lines without the fields are kept.
TEST(Train, ResumeKeepsTheLogLinesTheCheckpointHolds) {
  const std::string log =
      "{\"type\": \"step\", \"epoch\": 1, \"step\": 1, \"loss\": 2}\n"
      "{\"type\": \"step\", \"epoch\": 1, \"step\": 2, \"loss\": 1}\n"
      "{\"type\": \"note\"}\n"
      "{\"type\": \"epoch\", \"epoch\": 1, \"step\": 2}\n"
      "{\"type\": \"step\", \"epoch\": 2, \"step\": 3, \"loss\": 1}\n"
      "{\"type\": \"step\", \"epoch\": 1, \"step\": 99999999999999999999}\n"
      "{\"type\": \"eval\", \"epoch\": 1, \"st";
  EXPECT_EQ(kept_metrics_lines(log, 1, 2),
            "{\"type\": \"step\", \"epoch\": 1, \"step\": 1, \"loss\": 2}\n"
            "{\"type\": \"step\", \"epoch\": 1, \"step\": 2, \"loss\": 1}\n"
            "{\"type\": \"note\"}\n"
            "{\"type\": \"epoch\", \"epoch\": 1, \"step\": 2}\n");
  EXPECT_EQ(kept_metrics_lines(log, 0, 0), "{\"type\": \"note\"}\n");
  EXPECT_EQ(kept_metrics_lines("", 5, 5), "");
}

// A run directory's --resume with no checkpoint yet (a run killed in its first epoch) starts the
// run, and ends as a run started afresh does.
TEST(Train, ResumeWithoutACheckpointStartsTheRun) {
  const fs::path dir = test::temp_dir();
  train(options_for(dir / "fresh", tiny_config_text()));
  fs::create_directories(dir / "killed");
  const std::string torn = "{\"type\": \"step\", \"ep";  // a first line cut short
  write_file_atomic(dir / "killed" / "metrics.jsonl", torn.data(), torn.size());
  TrainOptions resumed = options_for(dir / "killed", tiny_config_text());
  resumed.resume = true;
  EXPECT_EQ(train(resumed).epochs_done, 2);
  EXPECT_EQ(read_file_bytes(dir / "fresh" / "checkpoint.safetensors"),
            read_file_bytes(dir / "killed" / "checkpoint.safetensors"));
  EXPECT_EQ(step_lines(dir / "fresh" / "metrics.jsonl"), step_lines(dir / "killed" / "metrics.jsonl"));
}

// TensorBoard's framing: CRC-32C's check value, and the scalars of a run read back from its
// event file (the losses of metrics.jsonl, steps 1..4).
TEST(Train, WritesTensorBoardEventFiles) {
  EXPECT_EQ(crc32c("123456789"), 0xE3069283u);
  const fs::path dir = test::temp_dir();
  train(options_for(dir / "run", tiny_config_text()));
  bool truncated = true;
  const std::vector<EventScalar> scalars = read_event_scalars(EventWriter::path_in(dir / "run"), &truncated);
  EXPECT_FALSE(truncated);
  std::vector<double> losses;
  for (const std::string& line : step_lines(dir / "run" / "metrics.jsonl")) {
    losses.push_back(std::stod(line.substr(line.find(R"("loss": )") + 8)));
  }
  std::vector<int64_t> steps;
  std::vector<float> values;
  for (const EventScalar& e : scalars) {
    if (e.tag != "train/loss") continue;
    steps.push_back(e.step);
    values.push_back(e.value);
    EXPECT_GT(e.wall_time, 1.7e9) << "seconds since 1970";
  }
  EXPECT_EQ(steps, (std::vector<int64_t>{1, 2, 3, 4}));
  ASSERT_EQ(values.size(), losses.size());
  for (size_t i = 0; i < values.size(); ++i) EXPECT_NEAR(values[i], losses[i], 1e-6 * std::abs(losses[i]) + 1e-6);
  EXPECT_EQ(std::count_if(scalars.begin(), scalars.end(), [](const EventScalar& e) { return e.tag == "train/epoch_mean_loss"; }), 2);
}

// train.loss ce+lovasz: the first step (same weights, same batch) costs the cross-entropy plus a
// Lovász term in (0, 1], and the run ends elsewhere than the cross-entropy's.
TEST(Train, LovaszTermAddsToTheCrossEntropy) {
  const fs::path dir = test::temp_dir();
  const auto first_loss = [](const fs::path& run) {
    const std::string line = step_lines(run / "metrics.jsonl").at(0);
    return std::stod(line.substr(line.find(R"("loss": )") + 8));
  };
  train(options_for(dir / "ce", tiny_config_text()));
  train(options_for(dir / "lovasz", tiny_config_text("  loss: ce+lovasz\n")));
  const double lovasz = first_loss(dir / "lovasz") - first_loss(dir / "ce");
  EXPECT_GT(lovasz, 0.05);
  EXPECT_LE(lovasz, 1.0 + 1e-6);
  EXPECT_NE(checkpoint_values(dir / "ce" / "checkpoint.safetensors"),
            checkpoint_values(dir / "lovasz" / "checkpoint.safetensors"));
}

// The loader's queue: items in order whatever the workers' timing, never more than `ahead` made
// and not taken, and 0 workers makes each item when it is taken.
TEST(Prefetcher, InOrderAndBounded) {
  for (const int workers : {0, 1, 4}) {
    std::atomic<int> made{0}, taken{0}, most_ahead{0};
    Prefetcher<int> p(50, workers, 3, [&](size_t i) {
      const int ahead = ++made - taken.load();
      int seen = most_ahead.load();
      while (ahead > seen && !most_ahead.compare_exchange_weak(seen, ahead)) {
      }
      std::this_thread::sleep_for(std::chrono::microseconds(50 * (i % 3)));
      return static_cast<int>(i * i);
    });
    for (size_t i = 0; i < 50; ++i) {
      EXPECT_EQ(p.take(i), static_cast<int>(i * i));
      ++taken;
    }
    EXPECT_LE(most_ahead.load(), workers == 0 ? 1 : 3 + 1) << workers << " workers";
    EXPECT_THROW(p.take(7), Error) << "out of order";
    Prefetcher<int> batches(10, workers, 4, [](size_t i) { return static_cast<int>(3 * i); });
    EXPECT_EQ(batches.take_batch(0, 4), (std::vector<int>{0, 3, 6, 9}));
    EXPECT_EQ(batches.take_batch(4, 6), (std::vector<int>{12, 15, 18, 21, 24, 27}));
    EXPECT_THROW(batches.take_batch(2, 1), Error) << "out of order";
  }
}

// train.workers: samples prepared ahead by 1 or 3 threads give the run of 0 workers bit for bit
// (each sample's randomness comes from (seed, epoch, index)), and each epoch logs its data wait.
TEST(Train, WorkersDoNotChangeTheResults) {
  const fs::path dir = test::temp_dir();
  train(options_for(dir / "w0", tiny_config_text()));
  for (const int workers : {1, 3}) {
    const std::string name = "w" + std::to_string(workers);
    train(options_for(dir / name, tiny_config_text(fmt::format("  workers: {}\n", workers))));
    EXPECT_EQ(checkpoint_values(dir / "w0" / "checkpoint.safetensors"),
              checkpoint_values(dir / name / "checkpoint.safetensors"))
        << workers << " workers";
    EXPECT_EQ(step_lines(dir / "w0" / "metrics.jsonl"), step_lines(dir / name / "metrics.jsonl"));
  }
  EXPECT_NE(read_file_text(dir / "w3" / "metrics.jsonl").find(R"("data_wait_s": )"), std::string::npos);
  EXPECT_THROW(parse_run_config(tiny_config_text("  workers: -1\n"), "test config"), Error);
}

// A bad scan stops a run with workers as it does without: its message, no hang.
TEST(Train, AWorkersFailureStopsTheRun) {
  const fs::path dir = test::temp_dir();
  const fs::path data = dir / "data";
  fs::copy(tiny_data(), data, fs::copy_options::recursive);
  // A truncated scan: 10 bytes are not a whole number of points.
  const fs::path scan = data / "sequences" / "00" / "velodyne" / "000001.bin";
  std::ofstream(scan, std::ios::binary | std::ios::trunc).write("0123456789", 10);
  TrainOptions o = options_for(dir / "run", tiny_config_text("  workers: 2\n"));
  o.data_root = data;
  try {
    train(o);
    FAIL() << "a truncated scan must stop training";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("000001.bin"), std::string::npos) << e.what();
  }
}

// eval.every_epochs: the validation's mIoU and per-class IoU in the log after every epoch, the
// best epoch's weights in best.safetensors (with its mIoU in the metadata, kept over a resume).
TEST(Train, ValidatesWhileTrainingAndKeepsTheBest) {
  const fs::path dir = test::temp_dir();
  std::string text = tiny_config_text();
  text.replace(text.find("eval: {sequences: [8]}"), 22, "eval: {sequences: [8], every_epochs: 1}");
  train(options_for(dir / "run", text));
  const std::string log = read_file_text(dir / "run" / "metrics.jsonl");
  std::vector<double> mious;
  std::istringstream in(log);
  for (std::string line; std::getline(in, line);) {
    if (line.find(R"("type": "eval")") == std::string::npos) continue;
    EXPECT_NE(line.find(R"("mode": "sparse")"), std::string::npos) << line;
    EXPECT_NE(line.find(R"("iou": {"vehicle": )"), std::string::npos) << line;
    const size_t at = line.find(R"("miou": )");
    ASSERT_NE(at, std::string::npos) << line;
    mious.push_back(std::stod(line.substr(at + 8)));
  }
  ASSERT_EQ(mious.size(), 2u) << log;
  ASSERT_TRUE(fs::exists(dir / "run" / "best.safetensors"));
  const Checkpoint best = read_checkpoint(dir / "run" / "best.safetensors");
  const Checkpoint last = read_checkpoint(dir / "run" / "checkpoint.safetensors");
  const double top = std::max(mious[0], mious[1]);
  EXPECT_NEAR(best.state.best_miou, top, 1e-6);
  EXPECT_EQ(best.state.best_epoch, mious[1] > mious[0] ? 2 : 1);
  EXPECT_FALSE(best.has_optimizer) << "best.safetensors holds the weights";
  EXPECT_NEAR(last.state.best_miou, top, 1e-6);
  // The last epoch was the best: best.safetensors holds its weights.
  if (mious[1] > mious[0]) {
    EXPECT_EQ(model_values(best), model_values(last));
  }
}

// --resume drops what a killed run logged after its checkpoint, in metrics.jsonl and in the event
// file (and the event file's cut-short last record): no step appears twice, and both are the
// uninterrupted run's.
TEST(Train, ResumeTruncatesTheMetricsLog) {
  const fs::path dir = test::temp_dir();
  train(options_for(dir / "straight", tiny_config_text()));
  TrainOptions first = options_for(dir / "killed", tiny_config_text());
  first.max_epochs_this_run = 1;
  train(first);
  // What a run killed during epoch 2 leaves after the epoch-1 checkpoint.
  std::ofstream(dir / "killed" / "metrics.jsonl", std::ios::app)
      << R"({"type": "step", "epoch": 2, "step": 3, "loss": 9.0, "lr": 1e-3, "beta1": 0.9, "grad_norm": 1.0, "elapsed_s": 1.00})"
      << "\n";
  // ... and in its event file: a step-3 scalar, then a record cut short by the kill.
  {
    const fs::path events = EventWriter::path_in(dir / "killed");
    const std::string before = read_file_text(events);
    {
      EventWriter writer(dir / "killed", /*resume=*/true, 1000);
      writer.scalar("train/loss", 3, 9.0);
    }
    std::ofstream(events, std::ios::binary | std::ios::app).write("\x20\x00\x00", 3);
    bool truncated = false;
    read_event_scalars(events, &truncated);
    EXPECT_TRUE(truncated);
    EXPECT_GT(read_file_text(events).size(), before.size());
  }
  TrainOptions second = options_for(dir / "killed", tiny_config_text());
  second.resume = true;
  train(second);
  EXPECT_EQ(step_lines(dir / "killed" / "metrics.jsonl"), step_lines(dir / "straight" / "metrics.jsonl"));
  const auto losses = [](const fs::path& run) {
    bool truncated = true;
    std::vector<std::pair<int64_t, float>> out;
    for (const EventScalar& e : read_event_scalars(EventWriter::path_in(run), &truncated))
      if (e.tag == "train/loss") out.emplace_back(e.step, e.value);
    EXPECT_FALSE(truncated) << run;
    return out;
  };
  EXPECT_EQ(losses(dir / "killed"), losses(dir / "straight"));
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
