// Training (DESIGN.md section 3): batches of augmented scans, weighted loss over labelled
// cells, backward, gradient-norm clipping, Adam with decoupled weight decay on the one-cycle
// (or constant) schedule. A checkpoint per epoch (atomic), exact resume from it, a metrics log
// (RUN_DIR/metrics.jsonl: one line per step and per epoch), and a clear stop on a non-finite
// loss that leaves the last good checkpoint in place.
//
// A run killed at any point (SIGKILL, an OOM kill, a preempted node) and resumed ends with the
// checkpoint an uninterrupted run writes, bit for bit, and a log with each step once: an epoch's
// logs are written before its checkpoint, the checkpoint is the commit point, and resume drops
// what came after the checkpoint it resumes from (tests/fault_test.sh).
#pragma once

#include <filesystem>
#include <optional>
#include <string>
#include <string_view>

#include "engine/backend/backend.hpp"
#include "core/replicas.hpp"
#include "engine/model/run_config.hpp"

namespace pillarseg {

struct TrainOptions {
  std::filesystem::path data_root;
  std::filesystem::path run_dir;
  RunConfig config;
  std::string device = "cpu";  // cpu, cuda or emu (make_backend)
  BackendOptions backend;      // the CUDA backends' Conv2d and device
  // The convolutions' arithmetic (--precision): BF16 / FP16 on the tensor cores of a backend that
  // supports_training_precision() it, with FP32 master weights and optimiser state; else the run
  // does not start.
  Precision precision = Precision::F32;
  std::optional<std::filesystem::path> cache_dir;
  // Continue the run in run_dir from its checkpoint; with none there yet (a run killed in its
  // first epoch), start it from the beginning.
  bool resume = false;
  bool progress = true;
  // Stop after this many epochs of this invocation (0: run to config.train.epochs); the
  // schedule still spans all epochs, so a stopped run resumes exactly.
  int max_epochs_this_run = 0;
  // Data-parallel training (`mpirun -np R pillarseg train`): this process's place among the R
  // replicas; nullptr: one process. train.batch_size is the global batch, a multiple of R, and
  // each replica takes its B / R scans of every batch (an epoch's incomplete last batch is padded
  // to a multiple of R with the epoch's first scans, as PyTorch's DistributedSampler pads).
  // Gradients, BatchNorm statistics (synchronised), the loss's normaliser and the validation's
  // confusion matrix are summed over the replicas in a fixed order; replica 0 alone writes the
  // run directory. The data root and the run directory are shared by all of them.
  Replicas* replicas = nullptr;
};

struct TrainResult {
  int64_t epochs_done = 0, steps_done = 0;
  double last_epoch_loss = 0;
  double wall_seconds = 0, cpu_seconds = 0;  // of this invocation (process CPU time, all threads)
  std::filesystem::path checkpoint;
};

TrainResult train(const TrainOptions& options);

// The lines of a metrics log to keep when resuming from the checkpoint of (epoch, step): those
// whose "epoch" and "step" fields do not exceed them, each ending in a newline; a last line
// without one (cut short by a killed writer) is dropped.
std::string kept_metrics_lines(std::string_view log, int64_t epoch, int64_t step);

// RUN_DIR/checkpoint.safetensors: the latest epoch's checkpoint.
std::filesystem::path latest_checkpoint(const std::filesystem::path& run_dir);

}  // namespace pillarseg
