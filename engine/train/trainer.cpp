#include "engine/train/trainer.hpp"

#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstring>
#include <ctime>
#include <limits>
#include <fstream>
#include <map>
#include <numeric>
#include <optional>

#include "core/error.hpp"
#include "core/fault.hpp"
#include "core/io.hpp"
#include "core/parallel.hpp"
#include "engine/eval/evaluate.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/pipeline/dataset.hpp"
#include "engine/pipeline/scan_pipeline.hpp"
#include "engine/pipeline/segmenter.hpp"
#include "engine/train/prefetcher.hpp"
#include "engine/util/progress.hpp"
#include "engine/util/tensorboard.hpp"
#include "host/adam.hpp"
#include "host/lr_schedule.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

fs::path latest_checkpoint(const fs::path& run_dir) {
  return run_dir / "checkpoint.safetensors";
}

namespace {

// The optimiser's settings are float values on every backend (what the CUDA kernel computes
// with; the CPU's steps equal those of earlier versions bit for bit). GCC folds
// (double)(float)x back to x in this file at -O3, so the rounding goes through a volatile float.
double float_value(double x) {
  const volatile float rounded = static_cast<float>(x);
  return rounded;
}

// Sample order of an epoch: a permutation drawn from its own stream.
std::vector<size_t> epoch_order(size_t n, uint64_t seed, uint64_t epoch) {
  std::vector<size_t> order(n);
  std::iota(order.begin(), order.end(), size_t{0});
  Rng rng = Rng::derive(seed, epoch, 0x5348554646ull);  // "SHUFF"
  rng.shuffle(order.begin(), order.end());
  return order;
}

}  // namespace

std::string kept_metrics_lines(std::string_view log, int64_t epoch, int64_t step) {
  // The value of `"name": <digits>` in a line, -1 if absent; digits too many for int64 read as
  // the largest value (a line from beyond any checkpoint).
  const auto field = [](std::string_view line, std::string_view name) -> int64_t {
    const std::string key = fmt::format("\"{}\": ", name);
    const size_t at = line.find(key);
    if (at == std::string_view::npos) return -1;
    const std::string_view rest = line.substr(at + key.size());
    int64_t value = 0;
    const auto [ptr, ec] = std::from_chars(rest.data(), rest.data() + rest.size(), value);
    if (ec == std::errc::result_out_of_range) return std::numeric_limits<int64_t>::max();
    return ec == std::errc() && ptr != rest.data() ? value : -1;
  };
  std::string kept;
  size_t begin = 0;
  while (begin < log.size()) {
    const size_t end = log.find('\n', begin);
    if (end == std::string_view::npos) break;  // cut short by a killed writer
    const std::string_view line = log.substr(begin, end - begin);
    begin = end + 1;
    if (field(line, "epoch") > epoch || field(line, "step") > step) continue;
    kept.append(line).push_back('\n');
  }
  return kept;
}

namespace {

// RUN_DIR/metrics.jsonl. On --resume the lines of what the checkpoint does not hold (the steps,
// epoch and validation lines of a run killed after it, and a last line it cut short) are dropped
// first (kept_metrics_lines), so that no step appears twice; the file is rewritten atomically.
class MetricsLog {
 public:
  MetricsLog(const fs::path& path, bool resume, const TrainState& state) : path_(path) {
    if (resume && fs::exists(path)) {
      const std::string kept = kept_metrics_lines(read_file_text(path), state.epoch, state.step);
      write_file_atomic(path, kept.data(), kept.size());
    }
    out_.open(path, resume ? std::ios::app : std::ios::trunc);
    PS_CHECK(out_, "{}: cannot open the metrics log for writing: {}", path.string(),
             std::strerror(errno));
  }
  void line(const std::string& json) {
    out_ << json << '\n';
    out_.flush();
    PS_CHECK(out_, "{}: cannot write the metrics log: {}", path_.string(),
             write_error_cause(errno));
  }

 private:
  fs::path path_;
  std::ofstream out_;
};

// {"road": 0.91, ...}: the per-class IoU (null where the class never occurs).
std::string iou_json(const SegmentationMetrics& m, const ClassTable& classes) {
  std::string out = "{";
  for (int c = 1; c <= kNumClasses; ++c) {
    const double v = m.iou(c);
    out += fmt::format("{}\"{}\": {}", c > 1 ? ", " : "", classes.name(c),
                       std::isfinite(v) ? fmt::format("{:.6f}", v) : "null");
  }
  return out + "}";
}

// [[...], ...]: the (12, 12) confusion matrix, row the true class, column the predicted one.
std::string confusion_json(const SegmentationMetrics& m) {
  const Tensor<int64_t>& c = m.confusion();
  std::string out = "[";
  for (int64_t r = 0; r < c.dim(0); ++r) {
    out += r > 0 ? ", [" : "[";
    for (int64_t k = 0; k < c.dim(1); ++k)
      out += fmt::format("{}{}", k > 0 ? ", " : "", c.data()[r * c.dim(1) + k]);
    out += "]";
  }
  return out + "]";
}

// A data-parallel replica's share of the batch at positions [begin, begin + count) of an
// epoch's order: the count padded to a multiple of the R replicas, R equal shares in replica
// order. Positions past the end of the epoch wrap to its first scans (take them modulo n).
struct Share {
  size_t first = 0, count = 0;
};
Share replica_share(size_t begin, size_t count, const Replicas& replicas) {
  const auto R = static_cast<size_t>(replicas.size());
  const size_t share = (count + R - 1) / R;
  return {begin + static_cast<size_t>(replicas.rank()) * share, share};
}

// The loss's class coefficients for this replica's share of a data-parallel batch: the losses
// are means over the labelled cells of the batch (host/losses.hpp), so a share with M_r of the
// batch's M labelled cells scales its coefficients by M_r / M, and the replicas' losses and
// gradients add up to the whole batch's.
std::array<float, 13> share_coefficients(const std::array<float, 13>& coefficients,
                                         const Tensor<uint8_t>& labels, Replicas& replicas) {
  int64_t cells[2] = {0, 0};  // this replica's labelled cells, all replicas'
  cells[0] = std::count_if(labels.data(), labels.data() + labels.numel(),
                           [](uint8_t l) { return l != 0; });
  cells[1] = cells[0];
  replicas.sum(&cells[1], 1);
  std::array<float, 13> scaled = coefficients;
  const double factor =
      cells[1] > 0 ? static_cast<double>(cells[0]) / static_cast<double>(cells[1]) : 0.0;
  for (float& c : scaled) c = static_cast<float>(c * factor);
  return scaled;
}

// Replicas that summed the same gradients in the same order hold the same parameters, running
// statistics and optimiser state bit for bit; a run whose replicas differ stops here.
void require_identical_replicas(const ParameterSet& ps, Replicas& replicas, int64_t epoch) {
  std::vector<int64_t> digests(static_cast<size_t>(replicas.size()), 0);
  uint64_t digest = 1469598103934665603ull;  // FNV-1a over the bytes of every array
  for (const std::vector<float>& host :
       {ps.download_flat(ps.values()), ps.download_flat(ps.buffers()), ps.download_adam_m(),
        ps.download_adam_v()}) {
    const auto* bytes = reinterpret_cast<const unsigned char*>(host.data());
    for (size_t i = 0; i < host.size() * sizeof(float); ++i)
      digest = (digest ^ bytes[i]) * 1099511628211ull;
  }
  digests[static_cast<size_t>(replicas.rank())] = static_cast<int64_t>(digest >> 1);
  replicas.sum(digests.data(), static_cast<int64_t>(digests.size()));
  for (int r = 1; r < replicas.size(); ++r) {
    PS_CHECK(
        digests[static_cast<size_t>(r)] == digests[0],
        "after epoch {}: the parameters of rank {} differ from rank 0's (the replicas diverged)",
        epoch, r);
  }
}

// Precise BatchNorm (train.precise_bn_batches): sets every running statistic to the mean of the
// batch statistics of K full batches of unaugmented training scans, spread evenly over the data
// set, under the current weights. Deterministic: the same scans in the same order every time.
// Data-parallel, each replica forwards its share of every batch (the statistics are synchronised).
// Its forwards are not training batches: num_batches_tracked keeps its count.
void recalibrate_batchnorm(PillarSegNet& net, const ScanDataset& data, const TrainConfig& tc,
                           const Replicas& replicas) {
  const std::map<std::string, int64_t> batches_tracked = net.parameters().counters();
  const size_t n = data.size();
  const size_t B = std::min(n, static_cast<size_t>(tc.batch_size));
  const size_t batches = std::clamp<size_t>(n / B, 1, static_cast<size_t>(tc.precise_bn_batches));
  const size_t used = batches * B;
  for (size_t k = 0; k < batches; ++k) {
    const Share share = replica_share(k * B, B, replicas);
    std::vector<Sample> samples(share.count);
    parallel_for(static_cast<int64_t>(share.count), [&](int64_t j) {
      const size_t slot = (share.first + static_cast<size_t>(j)) % used;
      samples[static_cast<size_t>(j)] =
          data.eval_sample(slot * n / used, tc.ground_truth, /*with_mask=*/false);
    });
    std::vector<const ScanInputs*> inputs;
    for (const Sample& sample : samples) inputs.push_back(&sample.inputs);
    net.set_batchnorm_momentum(1.0f / static_cast<float>(k + 1));
    net.forward(collate(inputs, net.config()), /*training=*/true);
  }
  net.set_batchnorm_momentum(0);
  net.parameters().counters() = batches_tracked;
}

// Whether the epoch `epochs_done` (1-based) ends inside train.average_epochs' window.
bool averaging(const TrainConfig& tc, int64_t epochs_done) {
  return epochs_done > tc.epochs - tc.average_epochs;
}

// Weight averaging (train.average_epochs = K), called at the end of each of the last K epochs:
// adds the trainable values to state.average_sum (in float, in the same order in a resumed run:
// the same bits), and after the last epoch sets the model to their mean and empties the sum.
// Precise BatchNorm, which runs next, then estimates the averaged weights' statistics. Every
// replica holds the same values, so each averages its own.
void average_weights(ParameterSet& ps, const TrainConfig& tc, TrainState& state, bool leader) {
  const std::vector<float> values = ps.download_flat(ps.values());
  if (state.average_sum.empty()) state.average_sum.assign(values.size(), 0.0f);
  for (size_t i = 0; i < values.size(); ++i) state.average_sum[i] += values[i];
  if (state.epoch < tc.epochs) return;
  const float k = static_cast<float>(tc.average_epochs);
  for (float& sum : state.average_sum) sum /= k;  // now the mean
  ps.upload_flat(ps.values(), state.average_sum);
  state.average_sum.clear();
  if (leader)
    spdlog::info("the model takes the mean of its weights at the end of the last {} epochs "
                 "(train.average_epochs)",
                 tc.average_epochs);
}

// Data-parallel training: each bucket of the gradients summed over the replicas as soon as the
// backward has finished it (Backend::begin_sum_over_replicas), and the begun sums moved along
// between the backward's nodes.
class ReplicaGradientSum final : public PillarSegNet::GradientListener {
 public:
  ReplicaGradientSum(Backend& backend, Replicas& replicas, const Ref& grads)
      : backend_(backend), replicas_(replicas), grads_(grads) {}
  void bucket_ready(int64_t offset, int64_t count) override {
    Ref bucket{grads_.data + offset, {count}};
    backend_.begin_sum_over_replicas(bucket, replicas_);
  }
  void between_nodes() override { replicas_.progress(); }

 private:
  Backend& backend_;
  Replicas& replicas_;
  Ref grads_;
};

}  // namespace

TrainResult train(const TrainOptions& options) {
  const RunConfig& cfg = options.config;
  const TrainConfig& tc = cfg.train;
  SingleProcess single_process;
  Replicas& replicas = options.replicas ? *options.replicas : single_process;
  const int R = replicas.size();
  const bool leader = replicas.leader();
  // The device and the data first: a run that cannot start leaves no run directory behind.
  auto backend = make_backend(options.device, options.backend);
  std::string why;
  PS_CHECK(backend->supports_training_precision(options.precision, &why),
           "train --precision {}: {}", precision_name(options.precision), why);
  if (R > 1) {
    PS_CHECK(backend->supports_synchronized_batchnorm(&why),
             "data-parallel training on {} ranks: {}", R, why);
    PS_CHECK(tc.batch_size % R == 0,
             "{}: train.batch_size {} is the global batch and must be a multiple of the {} ranks "
             "(each takes "
             "batch_size / ranks scans of every batch)",
             cfg.source, tc.batch_size, R);
  }
  const ClassTable classes = ClassTable::defaults();
  const bool augmented_dense = tc.ground_truth == GroundTruthKind::dense && tc.augment;
  ScanDataset data(options.data_root, tc.sequences, tc.scan_stride, tc.max_scans_per_sequence,
                   cfg.model, classes, tc.ground_truth, options.cache_dir, augmented_dense, cfg.input);
  if (tc.ground_truth == GroundTruthKind::dense) {
    // Replica 0 builds the cache; the others then read (and check) its entries.
    if (leader) data.build_cache(GroundTruthKind::dense);
    int64_t built = 0;
    replicas.sum(&built, 1);
    if (!leader) data.build_cache(GroundTruthKind::dense);
  }
  if (leader) fs::create_directories(options.run_dir);
  const fs::path ckpt_path = latest_checkpoint(options.run_dir);

  PillarSegNet net(cfg.model, *backend, tc.seed);
  net.set_training_precision(options.precision);
  if (R > 1) net.set_replicas(&replicas);
  ParameterSet& ps = net.parameters();
  const auto bucket_elements = static_cast<int64_t>(tc.gradient_bucket_mb * (1 << 20) / sizeof(float));
  bool buckets_said = false;
  // On a CUDA backend the decoration and the maps of each augmented scan are computed there
  // (engine/pipeline/scan_pipeline.hpp); the CPU backend's inputs come from the host pipeline.
  const bool on_device = backend->device() != Device::Cpu;
  ScanPipeline pipeline(cfg.model, *backend);

  TrainState state;
  // What a killed writer left: temporaries of this host's dead processes.
  if (leader) remove_stale_temporaries(options.run_dir, /*recursive=*/false);
  const bool resume = options.resume && fs::exists(ckpt_path);
  if (options.resume && !resume && leader)
    spdlog::info("--resume: no checkpoint in {} yet; starting the run from the beginning",
                 options.run_dir.string());
  if (resume) {
    const Checkpoint ckpt = read_checkpoint(ckpt_path);
    PS_CHECK(
        ckpt.config && ckpt.config->text == cfg.text,
        "--resume: {} was written with a different config than {}; resume with the same config",
        ckpt_path.string(), cfg.source);
    load_weights(ckpt, net, /*with_optimizer=*/true);
    state = ckpt.state;
    // Inside the averaging window (and before its last epoch) the checkpoint holds the sum.
    if (averaging(tc, state.epoch) && state.epoch < tc.epochs) {
      PS_CHECK(static_cast<int64_t>(state.average_sum.size()) == ps.num_trainable(),
               "--resume: {} holds {} values of {} for train.average_epochs {} at epoch {}, the "
               "model {}",
               ckpt_path.string(), state.average_sum.size(), kAverageSumName, tc.average_epochs,
               state.epoch, ps.num_trainable());
    }
    spdlog::info("resuming from {} (epoch {}, step {})", ckpt_path.string(), state.epoch,
                 state.step);
  } else {
    PS_CHECK(!fs::exists(ckpt_path),
             "{} exists: pass --resume to continue that run, or choose another --out",
             ckpt_path.string());
    if (leader)
      write_file_atomic(options.run_dir / "config.yaml", cfg.text.data(), cfg.text.size());
  }
  // The logs are replica 0's.
  std::optional<MetricsLog> log;
  std::optional<EventWriter> events;
  if (leader) {
    log.emplace(options.run_dir / "metrics.jsonl", resume, state);
    events.emplace(options.run_dir, resume, state.step);
  }
  const bool progress_bars = options.progress && leader;
  // Validation while training (eval.every_epochs): a segmenter of its own on the same device.
  std::unique_ptr<ScanSegmenter> validator;
  const fs::path best_path = options.run_dir / "best.safetensors";

  const size_t n = data.size();
  const size_t B = static_cast<size_t>(tc.batch_size);
  const int64_t steps_per_epoch = static_cast<int64_t>((n + B - 1) / B);
  host::LrScheduleOptions schedule;
  schedule.kind = tc.onecycle ? host::LrScheduleKind::kOneCycle : host::LrScheduleKind::kConstant;
  schedule.lr_max = tc.lr;
  schedule.total_steps = steps_per_epoch * tc.epochs;
  schedule.div_factor = tc.div_factor;
  schedule.pct_start = tc.pct_start;
  schedule.momentum_max = tc.momentum_max;
  schedule.momentum_min = tc.momentum_min;
  schedule.constant_beta1 = 0.9;

  if (leader) {
    spdlog::info(
        "training on {} scans ({} steps per epoch, batch {}), {} epochs, device {}, precision {}, "
        "{} threads{}",
        n, steps_per_epoch, B, tc.epochs, backend->name(), precision_name(options.precision),
        num_threads(),
        R > 1 ? fmt::format(" on each of {} ranks ({} scans of every batch each)", R,
                            B / static_cast<size_t>(R))
              : "");
  }
  TrainResult result;
  const int64_t last_epoch =
      options.max_epochs_this_run > 0
          ? std::min<int64_t>(tc.epochs, state.epoch + options.max_epochs_this_run)
          : tc.epochs;
  const auto started = std::chrono::steady_clock::now();
  const std::clock_t cpu_started = std::clock();
  // The end of a stop message: the checkpoint a user can resume from, if any.
  const auto last_good_checkpoint = [&] {
    return fs::exists(ckpt_path) ? fmt::format("The last good checkpoint is {}", ckpt_path.string())
                                 : std::string("No checkpoint was written yet.");
  };
  // train.workers: the epoch's samples, in its order, prepared ahead by that many threads (a
  // window of two batches per worker); with 0 each batch's samples in parallel when the step
  // needs them.
  const size_t ahead = 2 * B * static_cast<size_t>(std::max(tc.workers, 1));
  for (int64_t epoch = state.epoch; epoch < last_epoch; ++epoch) {
    const std::vector<size_t> order = epoch_order(n, tc.seed, static_cast<uint64_t>(epoch));
    // This replica's positions in the epoch's order, step by step (all of them with one).
    std::vector<size_t> mine;
    for (int64_t s = 0; s < steps_per_epoch; ++s) {
      const size_t begin = static_cast<size_t>(s) * B;
      const Share share = replica_share(begin, std::min(n, begin + B) - begin, replicas);
      for (size_t j = 0; j < share.count; ++j) mine.push_back(share.first + j);
    }
    std::optional<Prefetcher<TrainingScan>> scans_ahead;
    std::optional<Prefetcher<Sample>> samples_ahead;
    if (on_device) {
      scans_ahead.emplace(mine.size(), tc.workers, ahead, [&, epoch](size_t i) {
        return data.training_scan(order[mine[i] % n], static_cast<uint64_t>(epoch), tc);
      });
    } else {
      samples_ahead.emplace(mine.size(), tc.workers, ahead, [&, epoch](size_t i) {
        return data.training_sample(order[mine[i] % n], static_cast<uint64_t>(epoch), tc);
      });
    }
    Progress progress(fmt::format("epoch {}/{}", epoch + 1, tc.epochs), steps_per_epoch, "steps");
    double loss_sum = 0, data_wait = 0;
    double sum_wait = 0;  // data-parallel: host time from the backward's end to the sums' end
    size_t taken = 0;  // of mine
    for (int64_t s = 0; s < steps_per_epoch; ++s) {
      const size_t begin = static_cast<size_t>(s) * B;
      const size_t count = replica_share(begin, std::min(n, begin + B) - begin, replicas).count;
      const size_t first = taken;
      taken += count;
      Tensor<uint8_t> labels(
          {static_cast<int64_t>(count), cfg.model.grid.height(), cfg.model.grid.width()});
      const int64_t plane = cfg.model.grid.cells();
      const auto wait_started = std::chrono::steady_clock::now();
      const auto waited = [&] {
        data_wait +=
            std::chrono::duration<double>(std::chrono::steady_clock::now() - wait_started).count();
      };
      if (on_device) {
        const std::vector<TrainingScan> scans = scans_ahead->take_batch(first, count);
        waited();
        int64_t rows = 0;
        for (const TrainingScan& scan : scans) rows += scan.pillars.num_pillars();
        const PillarSegNet::Inputs inputs =
            net.prepare(static_cast<int>(scans.size()), rows, /*training=*/true);
        int64_t offset = 0;
        for (size_t k = 0; k < scans.size(); ++k) {
          const TrainingScan& scan = scans[k];
          const Ref points = pipeline.load_points(scan.points);
          const int64_t pillars = pipeline.upload_pillars(scan.pillars);
          pipeline.fill_pillars(points, pillars, static_cast<int>(k), offset, inputs);
          pipeline.fill_maps(points, scan.origin, static_cast<int>(k), inputs);
          offset += pillars;
          std::copy(scan.labels.begin(), scan.labels.end(),
                    labels.data() + static_cast<int64_t>(k) * plane);
        }
        net.run(/*training=*/true);
      } else {
        const std::vector<Sample> samples = samples_ahead->take_batch(first, count);
        waited();
        std::vector<const ScanInputs*> inputs;
        for (size_t k = 0; k < samples.size(); ++k) {
          inputs.push_back(&samples[k].inputs);
          std::copy(samples[k].labels.begin(), samples[k].labels.end(),
                    labels.data() + static_cast<int64_t>(k) * plane);
        }
        net.forward(collate(inputs, cfg.model), /*training=*/true);
      }
      double loss = 0;
      if (R > 1) {
        loss = net.loss(labels, LossSpec(tc.loss, 1.0f / static_cast<float>(R)),
                        share_coefficients(tc.coefficients, labels, replicas));
        replicas.sum(&loss, 1);
      } else {
        loss = net.loss(labels, tc.loss, tc.coefficients);
      }
      if (!std::isfinite(loss)) {
        PS_FAIL("non-finite loss ({}) at epoch {}, step {} (scans {}); stopping. {}", loss,
                epoch + 1, state.step + 1, data.describe(order[begin]), last_good_checkpoint());
      }
      Ref grads = ps.grads();
      if (R > 1) {
        ReplicaGradientSum summing(*backend, replicas, grads);
        net.backward(&summing, bucket_elements);
        const auto sums_started = std::chrono::steady_clock::now();
        backend->end_sums_over_replicas(replicas);
        sum_wait += std::chrono::duration<double>(std::chrono::steady_clock::now() - sums_started).count();
        if (leader && !buckets_said) {
          buckets_said = true;
          const size_t buckets = net.gradient_buckets(bucket_elements).size();
          spdlog::info("data-parallel: the gradients ({:.2f} MiB) are summed over the {} ranks in {} bucket{}{}",
                       static_cast<double>(grads.bytes()) / (1 << 20), R, buckets, buckets == 1 ? "" : "s",
                       buckets == 1 ? " after the backward"
                                    : fmt::format(" of at least {} MiB, each begun as the backward finishes it",
                                                  tc.gradient_bucket_mb));
        }
      } else {
        net.backward();
      }
      fault_point("step");
      const double grad_norm = std::sqrt(backend->sum_of_squares(grads));
      PS_CHECK(std::isfinite(grad_norm),
               "non-finite gradient norm at epoch {}, step {}; stopping. {}", epoch + 1,
               state.step + 1, last_good_checkpoint());
      if (tc.grad_clip > 0) {
        const double coefficient = host::clip_coefficient(grad_norm, tc.grad_clip);
        if (coefficient < 1) backend->scale(grads, static_cast<float>(coefficient));
      }
      const host::LrAndMomentum lm = host::lr_schedule_at(schedule, state.step);
      AdamOptions adam;
      adam.lr = float_value(lm.lr);
      adam.beta1 = float_value(lm.beta1);
      adam.beta2 = float_value(tc.beta2);
      adam.eps = float_value(tc.eps);
      adam.weight_decay = float_value(tc.weight_decay);
      Ref values = ps.values(), m = ps.adam_m(), v = ps.adam_v();
      backend->adam_step(values, grads, m, v, state.step + 1, adam);
      ++state.step;
      loss_sum += loss;
      const double elapsed =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
      if (!leader) continue;
      log->line(fmt::format(
          R"({{"type": "step", "epoch": {}, "step": {}, "loss": {:.6f}, "lr": {:.6e}, "beta1": {:.4f}, "grad_norm": {:.4f}, "elapsed_s": {:.2f}}})",
          epoch + 1, state.step, loss, lm.lr, lm.beta1, grad_norm, elapsed));
      events->scalar("train/loss", state.step, loss);
      events->scalar("train/lr", state.step, lm.lr);
      events->scalar("train/grad_norm", state.step, grad_norm);
      events->flush();
      if (progress_bars) progress.update(s + 1, fmt::format("loss {:.4f} lr {:.2e}", loss, lm.lr));
    }
    state.epoch = epoch + 1;
    result.last_epoch_loss = loss_sum / static_cast<double>(steps_per_epoch);
    if (progress_bars) {
      progress.finish(fmt::format("mean loss {:.4f}, waited {:.1f} s for data",
                                  result.last_epoch_loss, data_wait));
    }
    if (averaging(tc, state.epoch)) average_weights(ps, tc, state, leader);
    const int every = cfg.eval.every_epochs;
    const bool validate = every > 0 && (state.epoch % every == 0 || state.epoch == tc.epochs);
    // The running statistics are read only by the validation and by whoever takes the checkpoint
    // this run ends with (training normalises with the batch's own): precise BatchNorm runs where
    // they are read, and the checkpoints between hold the training's own averages.
    if (tc.precise_bn_batches > 0 && (validate || state.epoch == last_epoch))
      recalibrate_batchnorm(net, data, tc, replicas);
    if (R > 1) require_identical_replicas(ps, replicas, state.epoch);
    if (validate) {
      if (!validator) {
        SegmenterOptions vo;
        vo.flips = cfg.eval.flips;
        validator = std::make_unique<ScanSegmenter>(cfg.model, make_backend(options.device, options.backend), vo);
      }
      validator->net().parameters().copy_values_from(ps);
      EvalOptions eo;
      eo.data_root = options.data_root;
      eo.mode = cfg.eval.mode.value_or(tc.ground_truth);
      eo.cache_dir = options.cache_dir;
      eo.progress = progress_bars;
      eo.shard = replicas.rank(), eo.shards = R;  // each replica scores its share of the scans
      SegmentationMetrics m = evaluate(*validator, cfg, eo);
      if (R > 1) {
        Tensor<int64_t> confusion = m.confusion();
        replicas.sum(confusion.data(), confusion.numel());
        m = SegmentationMetrics(std::move(confusion));
      }
      const double miou = m.miou();
      const bool best = std::isfinite(miou) && miou > state.best_miou;
      if (best) {
        state.best_miou = miou, state.best_epoch = state.epoch;
        if (leader) save_checkpoint(best_path, net, cfg, state, /*with_optimizer=*/false);
      }
      if (!leader) continue;
      spdlog::info("epoch {}: {} mIoU {:.1f}% over {} labelled cells{}", state.epoch,
                   eval_mode_label(tc.ground_truth, eo.mode), 100.0 * miou, m.labelled_cells(),
                   best ? fmt::format(" (best so far: {})", best_path.string()) : "");
      log->line(fmt::format(
          R"({{"type": "eval", "epoch": {}, "step": {}, "mode": "{}", "miou": {}, "labelled_cells": {}, "best_epoch": {}, "iou": {}, "confusion": {}}})",
          state.epoch, state.step, to_string(eo.mode),
          std::isfinite(miou) ? fmt::format("{:.6f}", miou) : "null", m.labelled_cells(),
          state.best_epoch, iou_json(m, classes), confusion_json(m)));
      if (std::isfinite(miou)) events->scalar("val/miou", state.step, miou);
      for (int c = 1; c <= kNumClasses; ++c) {
        if (std::isfinite(m.iou(c)))
          events->scalar("val/iou/" + classes.name(c), state.step, m.iou(c));
      }
    }
    if (!leader) continue;
    // The epoch's logs first, its checkpoint last: the checkpoint commits the epoch (a resume
    // from the one before drops these lines again).
    events->scalar("train/epoch_mean_loss", state.step, result.last_epoch_loss);
    events->scalar("train/data_wait_s", state.step, data_wait);
    if (R > 1) events->scalar("train/gradient_sum_wait_s", state.step, sum_wait);
    events->flush();
    log->line(fmt::format(
        R"({{"type": "epoch", "epoch": {}, "step": {}, "mean_loss": {:.6f}, "data_wait_s": {:.3f}{}, "checkpoint": "{}"}})",
        state.epoch, state.step, result.last_epoch_loss, data_wait,
        R > 1 ? fmt::format(R"(, "gradient_sum_wait_s": {:.3f})", sum_wait) : "", ckpt_path.filename().string()));
    save_checkpoint(ckpt_path, net, cfg, state, /*with_optimizer=*/true);
  }
  result.epochs_done = state.epoch;
  result.steps_done = state.step;
  result.wall_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  result.cpu_seconds = static_cast<double>(std::clock() - cpu_started) / CLOCKS_PER_SEC;
  result.checkpoint = ckpt_path;
  return result;
}

}  // namespace pillarseg
