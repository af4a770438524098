// pillarseg train / eval: training with checkpoints and exact resume; evaluation as the
// paper's Table I (Markdown) and JSON.
#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cstdlib>
#include <optional>

#include "core/io.hpp"
#include "core/memory_budget.hpp"
#include "engine/cli/cli_util.hpp"
#include "engine/cli/commands.hpp"
#include "engine/eval/evaluate.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/memory_estimate.hpp"
#include "engine/train/trainer.hpp"
#if defined(PILLARSEG_HAVE_MPI)
#include "engine/mpi/mpi_replicas.hpp"
#endif

namespace pillarseg::cli {

namespace {

// Whether this process was started by mpirun (OpenMPI's or a PMIx launcher's variables).
bool launched_by_mpirun() {
  for (const char* name : {"OMPI_COMM_WORLD_SIZE", "PMIX_RANK", "PMI_RANK"}) {
    if (std::getenv(name) != nullptr) return true;
  }
  return false;
}

struct TrainArgs {
  std::string data, config, out, cache;
  DeviceArgs device;
  bool resume = false;
  int epochs_now = 0;
};

struct EvalArgs {
  std::string data, weights, config, mode = "sparse", cache, report;
  DeviceArgs device;
  std::vector<int> sequences;
  int stride = 0;
  int flips = 0;  // 0: the config's eval.flips
};

// Training's memory, checked before the trainer reads any data: on the host for the CPU backend and
// the emulation (the trainer checks a GPU's when it plans the model); this process's share of the
// batch in a data-parallel run.
void check_training_memory(const TrainOptions& o) {
  if (o.device != "cpu" && o.device != "emu") return;
  const int ranks = o.replicas ? o.replicas->size() : 1;
  check_model_memory(o.config.model, std::max(1, o.config.train.batch_size / ranks), /*training=*/true,
                     host_memory_budget());
}

void run_train(const TrainArgs& a) {
  TrainOptions o;
  o.data_root = a.data;
  o.run_dir = a.out;
  o.config = load_run_config(a.config);
  o.device = a.device.device;
  o.backend = {a.device.conv, a.device.cuda_device};
  o.precision = parse_precision(a.device.precision);
  if (!a.cache.empty()) o.cache_dir = a.cache;
  o.resume = a.resume;
  o.max_epochs_this_run = a.epochs_now;
  // Started by mpirun: one replica of a data-parallel run (DESIGN.md section 8).
  const bool under_mpirun = launched_by_mpirun();
#if defined(PILLARSEG_HAVE_MPI)
  std::optional<MpiReplicas> replicas;
  if (under_mpirun) {
    replicas.emplace();
    if (replicas->size() > 1) o.replicas = &*replicas;
    // One GPU per rank: --cuda-device is the node's first, rank r uses the (local rank r)-th after it.
    const char* local = std::getenv("OMPI_COMM_WORLD_LOCAL_RANK");
    if (local != nullptr && o.replicas && o.device == "cuda") {
      o.backend.cuda_device += std::atoi(local);
    }
    // One replica speaks; the others only report errors.
    if (!replicas->leader()) spdlog::set_level(spdlog::level::err);
  }
  TrainResult r;
  try {
    check_training_memory(o);
    r = train(o);
  } catch (const std::exception& e) {
    // A failing rank stops all of them, with its message (the others would wait for it forever).
    if (o.replicas) replicas->abort_all(e.what());
    throw;
  }
  if (o.replicas && !replicas->leader()) return;
#else
  PS_CHECK(!under_mpirun,
           "pillarseg train was started by mpirun, but this build has no MPI (install Debian's "
           "libopenmpi-dev and "
           "rebuild) for data-parallel training");
  check_training_memory(o);
  const TrainResult r = train(o);
#endif
  fmt::print(
      "trained {} epochs ({} steps) in {:.1f} min ({:.1f} CPU-min), last epoch mean loss {:.4f}; "
      "checkpoint {}\n",
      r.epochs_done, r.steps_done, r.wall_seconds / 60, r.cpu_seconds / 60, r.last_epoch_loss,
      r.checkpoint.string());
}

void run_eval(const EvalArgs& a) {
  const Checkpoint ckpt = read_checkpoint(a.weights);
  const RunConfig config = config_for(ckpt, a.config);
  SegmenterOptions options = segmenter_options(a.device);
  options.flips = a.flips > 0 ? a.flips : config.eval.flips;
  const std::unique_ptr<ScanSegmenter> segmenter = open_segmenter(ckpt, config, a.weights, options);
  EvalOptions o;
  o.data_root = a.data;
  o.mode = parse_ground_truth_kind(a.mode);
  o.sequences = a.sequences;
  o.scan_stride = a.stride;
  if (!a.cache.empty()) o.cache_dir = a.cache;
  const SegmentationMetrics m = evaluate(*segmenter, config, o);
  const ClassTable classes = ClassTable::defaults();
  const std::string mode = eval_mode_label(config.train.ground_truth, o.mode),
                    method = method_label(config.model) +
                             (options.flips > 1 ? fmt::format(" ({} flips)", options.flips) : "");
  fmt::print("\n{}\n", m.markdown_table(classes, mode, method));
  fmt::print("mIoU {:.1f}% over {} labelled cells{}\n", 100.0 * m.miou(), m.labelled_cells(),
             options.flips > 1 ? fmt::format(", each scan's softmax the mean of {} mirrored copies", options.flips)
                               : "");
  const std::string report = a.report.empty()
                                 ? std::filesystem::path(a.weights).replace_extension().string() +
                                       "." + a.mode + "_eval.json"
                                 : a.report;
  const std::string json = m.json(classes, mode, method);
  write_file_atomic(report, json.data(), json.size());
  fmt::print("report: {}\n", report);
}

}  // namespace

void add_train(CLI::App& app) {
  auto a = std::make_shared<TrainArgs>();
  CLI::App* cmd =
      app.add_subcommand("train", "Train PillarSegNet; a checkpoint per epoch in --out");
  cmd->add_option("--data", a->data, "SemanticKITTI root (holds sequences/)")->required();
  cmd->add_option("--config", a->config, "run config YAML (configs/*.yaml)")
      ->required()
      ->check(CLI::ExistingFile);
  cmd->add_option("--out", a->out,
                  "run directory: checkpoint.safetensors, metrics.jsonl, config.yaml")
      ->required();
  cmd->add_flag("--resume", a->resume,
                "continue the run in --out from its checkpoint (with none there yet: start it)");
  cmd->add_option("--epochs-now", a->epochs_now,
                  "stop after this many epochs of this invocation (resume later)")
      ->check(CLI::NonNegativeNumber);
  add_device_options(cmd, a->device);
  cmd->add_option("--cache", a->cache, "ground-truth cache directory");
  cmd->callback([a] { run_train(*a); });

  auto e = std::make_shared<EvalArgs>();
  CLI::App* ev = app.add_subcommand(
      "eval", "Evaluate a checkpoint: per-class IoU and mIoU (Table I layout) + JSON");
  ev->add_option("--data", e->data, "SemanticKITTI root")->required();
  ev->add_option("--weights", e->weights, "checkpoint (.safetensors)")->required();
  ev->add_option("--mode", e->mode, "sparse or dense ground truth")
      ->check(CLI::IsMember({"sparse", "dense"}));
  ev->add_option("--config", e->config, "run config (default: the one stored in the checkpoint)");
  ev->add_option("--sequences", e->sequences,
                 "sequences to evaluate (default: the config's eval.sequences)");
  ev->add_option("--stride", e->stride, "every n-th scan (default: the config's eval.scan_stride)");
  add_flips_option(ev, e->flips, " (default: the config's eval.flips, else 1)");
  add_device_options(ev, e->device);
  ev->add_option("--cache", e->cache, "ground-truth cache directory");
  ev->add_option("--report", e->report, "JSON report path (default: beside the checkpoint)");
  ev->callback([e] { run_eval(*e); });
}

}  // namespace pillarseg::cli
