// PillarSegNet on the CPU (engine/model on the CpuBackend) against PyTorch on the same network,
// input and thread count, in one run. This machine is shared and its load drifts, so every
// comparison alternates the two sides step by step (ours then PyTorch, then PyTorch then ours)
// and reports the median of the per-step ratios. PyTorch is bench/peer/pytorch_peer.py --serve
// run by /usr/bin/python3 in its own process, one step per command on its stdin. Benchmarks:
//   Gemm/4096/threads:T     C (4096 x 4096) = A * B in fp32 with Eigen: the machine's matrix-
//                           product rate; threads 1 is one Eigen call, threads T splits the
//                           rows of A over OpenMP (the build defines EIGEN_DONT_PARALLELIZE).
//   Conv3x3/<layer>         the CPU backend's 3x3 conv (Winograd) at each 3x3 conv shape of the
//                           full-size U-Nets, x (1, I, h, w) -> y (1, O, h, w), against the
//                           GEMM's rate, the host/ reference and PyTorch's nn.Conv2d.
//   Model/<size>/<variant>/<forward|train>
//                           forward: eval mode (PyTorch: under no_grad); train: training-mode
//                           forward + weighted cross-entropy + backward + gradient-norm clip 10
//                           + Adam(W) step; PyTorch reads the same pillars and labels, written
//                           to a temporary directory.
// Sizes: full = the paper's (grid 1000 x 500 cells of 0.1 m, C = b = 64, depth 4, batch 1);
// small (--small) = the CPU configs' (0.2 m cells: 500 x 250, C = b = 16, batch 2). Variants:
// bilinear (the authors' UNet(64, 12)) and transposed. Input: simulated scans (engine/sim:
// 64-beam LiDAR in a procedural street), or a labelled SemanticKITTI scan given with --scan,
// -> every non-empty pillar, N = 20 points, decorated (P, N, 10); labels: the sparse ground
// truth (B, H, W).
// FLOPs: 2 x the multiply-adds of every conv, transposed conv and linear layer of one forward,
// from the model's parameter shapes and the level each runs at; a training step counts 3 x
// that (each layer's backward computes dx and dw, each as many multiply-adds as its forward).
// Each model case: one warm-up step on each side, then --reps timed steps each; reported:
// median wall ms, GFLOP/s at it, the median process CPU time of a step (all threads: on a
// shared machine it varies less with the load than the wall time does), and the peak RSS of
// the case (ours: getrusage ru_maxrss after resetting the process's high-water mark through
// /proc/self/clear_refs; PyTorch: VmHWM of its own process). Tables at the end: the conv layers,
// ours vs PyTorch, where our time goes per backend op (a timing decorator around the CpuBackend)
// and, with --peer_profile, where PyTorch's goes.
//
// Own flags (Google Benchmark's, such as --benchmark_filter=REGEX, work as well):
//   --threads=T (default 0: all hardware threads)  --reps=R (timed steps per model case, 1)
//   --layer_reps=R (per conv layer and GEMM, 1)  --small (add the small size)  --no_peer (skip
//   PyTorch)  --peer_profile (print PyTorch's time by op, from one more step under its profiler)
//   --scan=PATH.bin (a SemanticKITTI scan; labels from ../labels/NNNNNN.label)
//   --peer_python=PATH (default /usr/bin/python3)  --peer_script=PATH (default beside this file)
#include <benchmark/benchmark.h>
#include <fcntl.h>
#include <fmt/format.h>
#include <spawn.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <numeric>
#include <optional>
#include <sstream>
#include <string>
#include <type_traits>
#include <vector>

// GCC 12 flags its own AVX-512 intrinsics, inlined into Eigen's GEMM packing, as reading an
// uninitialised value (GCC bug 105593, fixed in GCC 13); the warnings are silenced for Eigen only.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
#include <Eigen/Core>
#pragma GCC diagnostic pop

#include "engine/core/error.hpp"
#include "engine/core/io.hpp"
#include "engine/core/parallel.hpp"
#include "engine/core/rng.hpp"
#include "engine/data/classes.hpp"
#include "engine/data/ground_truth.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/model/backend.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/sim/simulate.hpp"
#include "host/conv2d.hpp"
#include "host/pillar_gather.hpp"
#include "host/point_decoration.hpp"

using namespace pillarseg;

namespace {

using Clock = std::chrono::steady_clock;

// ---- options ----

struct Options {
  int threads = 0;  // 0: all hardware threads
  int reps = 1;
  int layer_reps = 1;
  bool small = false;
  std::filesystem::path scan;  // empty: simulated scans
  bool peer = true;
  bool peer_profile = false;
  std::string peer_python = "/usr/bin/python3";
  std::filesystem::path peer_script =
      std::filesystem::path(__FILE__).parent_path() / "peer" / "pytorch_peer.py";
};

Options g_options;

// Takes this benchmark's own flags out of argv (Google Benchmark rejects flags it does not know).
Options parse_options(int& argc, char** argv) {
  Options o;
  int kept = 1;
  // The integer after "--name=" in arg, at least `minimum`.
  const auto int_value = [](const std::string& arg, int minimum) {
    const std::string text = arg.substr(arg.find('=') + 1);
    size_t used = 0;
    int v = 0;
    try {
      v = std::stoi(text, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    PS_CHECK(used == text.size() && !text.empty() && v >= minimum,
             "{}: expected an integer >= {} after '=', got '{}'", arg, minimum, text);
    return v;
  };
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg.rfind("--threads=", 0) == 0) {
      o.threads = int_value(arg, 0);
    } else if (arg.rfind("--reps=", 0) == 0) {
      o.reps = int_value(arg, 1);
    } else if (arg.rfind("--layer_reps=", 0) == 0) {
      o.layer_reps = int_value(arg, 1);
    } else if (arg == "--small") {
      o.small = true;
    } else if (arg == "--no_peer") {
      o.peer = false;
    } else if (arg == "--peer_profile") {
      o.peer_profile = true;
    } else if (arg.rfind("--scan=", 0) == 0) {
      o.scan = arg.substr(7);
    } else if (arg.rfind("--peer_python=", 0) == 0) {
      o.peer_python = arg.substr(14);
    } else if (arg.rfind("--peer_script=", 0) == 0) {
      o.peer_script = arg.substr(14);
    } else {
      argv[kept++] = argv[i];
    }
  }
  argc = kept;
  return o;
}

// CPU time of this process, all threads, in seconds.
double process_cpu_seconds() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

double median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 == 1 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

// Wall and process CPU seconds of each timed step.
struct StepTimes {
  std::vector<double> wall, cpu;
  double wall_median() const { return median(wall); }
  double cpu_median() const { return median(cpu); }
  void add(double wall_seconds, double cpu_seconds) {
    wall.push_back(wall_seconds);
    cpu.push_back(cpu_seconds);
  }
};

// Runs step() once, adds its times to `times` and returns its wall seconds.
template <class Step>
double time_once(StepTimes& times, Step&& step) {
  const Clock::time_point start = Clock::now();
  const double cpu_start = process_cpu_seconds();
  step();
  const double cpu = process_cpu_seconds() - cpu_start;
  times.add(std::chrono::duration<double>(Clock::now() - start).count(), cpu);
  return times.wall.back();
}

// Median over steps i of a[i] / b[i]: the ratio of two step series measured alternately.
double median_ratio(const std::vector<double>& a, const std::vector<double>& b) {
  std::vector<double> ratios;
  for (size_t i = 0; i < std::min(a.size(), b.size()); ++i) ratios.push_back(a[i] / b[i]);
  return median(ratios);
}

// ---- peak resident memory of one case ----

// Resets the process's RSS high-water mark (Linux: writing 5 to /proc/self/clear_refs), so that
// ru_maxrss afterwards is the peak of what runs from now on. False where that is not possible.
bool reset_peak_rss() {
  std::ofstream clear("/proc/self/clear_refs");
  clear << "5";
  clear.flush();
  return static_cast<bool>(clear);
}

double peak_rss_mb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0;  // ru_maxrss is in KiB
}

// ---- the network's layers and FLOPs ----

// One multiply-add layer of a forward. conv: output (batch, out, h, w) with a k x k kernel;
// transposed (k = 2, stride 2): input (batch, in, h, w); linear: rows = h.
struct Layer {
  enum class Kind { Conv, Transposed, Linear } kind = Kind::Conv;
  std::string name;
  int64_t batch = 1, in = 0, out = 0, k = 1, h = 1, w = 1;

  double flops() const {
    const double macs = static_cast<double>(batch * in * out * k * k) * static_cast<double>(h * w);
    return 2.0 * macs;
  }
};

// Level (0 = input resolution, i = after i poolings) of a U-Net parameter, from its name:
// downI runs at level I, upJ's convs at depth - J, upJ's transposed conv reads level depth-J+1,
// outc and the occupancy stream at 0.
int level_of(const std::string& name, int depth) {
  const auto number_after = [&](const std::string& prefix) {
    return std::stoi(name.substr(prefix.size()));
  };
  if (name.rfind("segmentation_head.down", 0) == 0) return number_after("segmentation_head.down");
  if (name.rfind("segmentation_head.up", 0) == 0) {
    const int j = number_after("segmentation_head.up");
    return name.find(".up.weight") != std::string::npos ? depth - j + 1 : depth - j;
  }
  return 0;
}

// Every conv, transposed conv and linear layer of the model's forward for `batch` samples and
// `pillars` pillars, read from its parameters: weights of rank 4 are convs (O, I, k, k) or,
// named up.weight, transposed convs (I, O, 2, 2); the PFN's linear weight is (C, 10).
std::vector<Layer> forward_layers(const PillarSegNet& net, int batch, int64_t pillars) {
  const ModelConfig& c = net.config();
  std::vector<int64_t> hs{c.grid.height()}, ws{c.grid.width()};
  for (int i = 1; i <= c.depth; ++i) hs.push_back(hs.back() / 2), ws.push_back(ws.back() / 2);
  std::vector<Layer> layers;
  for (const ParamEntry& e : net.parameters().entries()) {
    if (!e.trainable) continue;
    Layer l;
    l.name = e.name.substr(0, e.name.rfind('.'));
    if (e.name == "vfe.pfn_layers.0.linear.weight") {
      l.kind = Layer::Kind::Linear;
      l.out = e.shape[0], l.in = e.shape[1], l.h = pillars * c.max_points_per_pillar;
    } else if (e.shape.size() == 4) {
      const size_t level = static_cast<size_t>(level_of(e.name, c.depth));
      const bool transposed = e.name.find(".up.weight") != std::string::npos;
      l.kind = transposed ? Layer::Kind::Transposed : Layer::Kind::Conv;
      l.batch = batch;
      l.in = transposed ? e.shape[0] : e.shape[1];
      l.out = transposed ? e.shape[1] : e.shape[0];
      l.k = e.shape[2], l.h = hs.at(level), l.w = ws.at(level);
    } else {
      continue;
    }
    layers.push_back(l);
  }
  return layers;
}

double total_flops(const std::vector<Layer>& layers) {
  double sum = 0.0;
  for (const Layer& l : layers) sum += l.flops();
  return sum;
}

// ---- the backend with a stopwatch per op ----

struct OpTotal {
  double seconds = 0.0, flops = 0.0;
  int64_t calls = 0;
};

// Forwards every Backend call to `inner` and adds its wall time (and, for the convolutions, its
// multiply-add count x 2) to a total per op. The CPU backend is synchronous, so a call's wall
// time is the op's time.
class TimedBackend final : public Backend {
 public:
  explicit TimedBackend(std::unique_ptr<Backend> inner) : inner_(std::move(inner)) {}

  const std::map<std::string, OpTotal>& totals() const { return totals_; }
  void clear_totals() { totals_.clear(); }

  Device device() const override { return inner_->device(); }
  std::string name() const override { return "timed " + inner_->name(); }
  void* allocate(size_t bytes) override { return inner_->allocate(bytes); }
  void deallocate(void* p) noexcept override { inner_->deallocate(p); }
  void upload(void* dst, const void* src, size_t bytes) override {
    timed("memory: upload, fill", 0, [&] { inner_->upload(dst, src, bytes); });
  }
  void download(void* dst, const void* src, size_t bytes) override {
    timed("memory: upload, fill", 0, [&] { inner_->download(dst, src, bytes); });
  }
  void fill_zero(void* dst, size_t bytes) override {
    timed("memory: upload, fill", 0, [&] { inner_->fill_zero(dst, bytes); });
  }

  void pfn_forward(const Ref& points, const Ref& weight, BatchNormRefs& bn, bool training,
                   IRef& argmax, Ref& out, const Ref& scratch) override {
    timed("pfn forward", linear_flops(points, weight),
          [&] { inner_->pfn_forward(points, weight, bn, training, argmax, out, scratch); });
  }
  void pfn_backward(const Ref& points, const Ref& weight, const BatchNormRefs& bn,
                    const IRef& argmax, const Ref& dout, Ref& d_points, Ref& dweight, Ref& dgamma,
                    Ref& dbeta, const Ref& scratch) override {
    timed("pfn backward", 2 * linear_flops(points, weight), [&] {
      inner_->pfn_backward(points, weight, bn, argmax, dout, d_points, dweight, dgamma, dbeta,
                           scratch);
    });
  }
  void scatter_forward(const Ref& features, const IRef& cells, int channel0, Ref& canvas) override {
    timed("scatter forward", 0,
          [&] { inner_->scatter_forward(features, cells, channel0, canvas); });
  }
  void scatter_backward(const Ref& dcanvas, const IRef& cells, int channel0,
                        Ref& dfeatures) override {
    timed("scatter backward", 0,
          [&] { inner_->scatter_backward(dcanvas, cells, channel0, dfeatures); });
  }
  void copy_channels(const Ref& x, int channel0, Ref& y) override {
    timed("channel copies", 0, [&] { inner_->copy_channels(x, channel0, y); });
  }
  void extract_channels(const Ref& y, int channel0, Ref& x) override {
    timed("channel copies", 0, [&] { inner_->extract_channels(y, channel0, x); });
  }

  void conv2d_forward(const Ref& x, const Ref& w, const Ref* bias, int pad, Ref& y) override {
    timed(conv_op(w, "forward"), conv_flops(y, w),
          [&] { inner_->conv2d_forward(x, w, bias, pad, y); });
  }
  void conv2d_bn_relu_eval(const Ref& x, const Ref& w, const Ref* bias, const BatchNormRefs& bn,
                           int pad, Ref& y) override {
    timed(conv_op(w, "+BN+ReLU eval"), conv_flops(y, w),
          [&] { inner_->conv2d_bn_relu_eval(x, w, bias, bn, pad, y); });
  }
  void conv2d_backward(const Ref& x, const Ref& w, const Ref& dy, int pad, Ref* dx, Ref& dw,
                       Ref* dbias) override {
    const double passes = dx != nullptr ? 2.0 : 1.0;  // dw, and dx when asked for
    timed(conv_op(w, "backward"), passes * conv_flops(dy, w),
          [&] { inner_->conv2d_backward(x, w, dy, pad, dx, dw, dbias); });
  }
  void conv_transpose2d_forward(const Ref& x, const Ref& w, const Ref* bias, Ref& y) override {
    timed("convT 2x2 forward", transposed_flops(x, w),
          [&] { inner_->conv_transpose2d_forward(x, w, bias, y); });
  }
  void conv_transpose2d_backward(const Ref& x, const Ref& w, const Ref& dy, Ref& dx, Ref& dw,
                                 Ref* dbias) override {
    timed("convT 2x2 backward", 2 * transposed_flops(x, w),
          [&] { inner_->conv_transpose2d_backward(x, w, dy, dx, dw, dbias); });
  }
  void batchnorm_relu_forward(const Ref& x, BatchNormRefs& bn, bool training, Ref& y) override {
    timed("batchnorm+relu forward", 0, [&] { inner_->batchnorm_relu_forward(x, bn, training, y); });
  }
  void batchnorm_relu_backward(const Ref& x, const Ref& y, const Ref& dy, const BatchNormRefs& bn,
                               Ref& dx, Ref& dgamma, Ref& dbeta) override {
    timed("batchnorm+relu backward", 0,
          [&] { inner_->batchnorm_relu_backward(x, y, dy, bn, dx, dgamma, dbeta); });
  }
  void maxpool2x2_forward(const Ref& x, Ref& y, IRef& argmax) override {
    timed("maxpool forward", 0, [&] { inner_->maxpool2x2_forward(x, y, argmax); });
  }
  void maxpool2x2_backward(const Ref& dy, const IRef& argmax, Ref& dx) override {
    timed("maxpool backward", 0, [&] { inner_->maxpool2x2_backward(dy, argmax, dx); });
  }
  void upsample2x_forward(const Ref& x, Ref& y) override {
    timed("upsample forward", 0, [&] { inner_->upsample2x_forward(x, y); });
  }
  void upsample2x_backward(const Ref& dy, Ref& dx) override {
    timed("upsample backward", 0, [&] { inner_->upsample2x_backward(dy, dx); });
  }
  void pad_concat_forward(const Ref& skip, const Ref& up, Ref& y) override {
    timed("pad+concat forward", 0, [&] { inner_->pad_concat_forward(skip, up, y); });
  }
  void pad_concat_backward(const Ref& dy, Ref& dskip, Ref& dup) override {
    timed("pad+concat backward", 0, [&] { inner_->pad_concat_backward(dy, dskip, dup); });
  }
  void add_inplace(Ref& a, const Ref& b) override {
    timed("add (skip gradients)", 0, [&] { inner_->add_inplace(a, b); });
  }
  void softmax(const Ref& logits, Ref& probs) override {
    timed("softmax, argmax", 0, [&] { inner_->softmax(logits, probs); });
  }
  void argmax(const Ref& logits, LRef& labels) override {
    timed("softmax, argmax", 0, [&] { inner_->argmax(logits, labels); });
  }
  double loss(LossKind kind, const Ref& logits, const LRef& labels, const Ref& coefficients,
              Ref& dlogits) override {
    return timed("loss", 0,
                 [&] { return inner_->loss(kind, logits, labels, coefficients, dlogits); });
  }
  double sum_of_squares(const Ref& x) override {
    return timed("optimizer: norm, clip, adam", 0, [&] { return inner_->sum_of_squares(x); });
  }
  void scale(Ref& x, float factor) override {
    timed("optimizer: norm, clip, adam", 0, [&] { inner_->scale(x, factor); });
  }
  void adam_step(Ref& param, const Ref& grad, Ref& m, Ref& v, const AdamHyper& hyper) override {
    timed("optimizer: norm, clip, adam", 0, [&] { inner_->adam_step(param, grad, m, v, hyper); });
  }

 private:
  template <class Fn>
  std::invoke_result_t<Fn&> timed(const std::string& op, double flops, Fn&& fn) {
    const Clock::time_point start = Clock::now();
    const auto add = [&] {
      OpTotal& t = totals_[op];
      t.seconds += std::chrono::duration<double>(Clock::now() - start).count();
      t.flops += flops;
      ++t.calls;
    };
    if constexpr (std::is_void_v<std::invoke_result_t<Fn&>>) {
      fn();
      add();
    } else {
      auto result = fn();
      add();
      return result;
    }
  }
  static std::string conv_op(const Ref& w, const char* pass) {
    return fmt::format("conv{}x{} {}", w.dim(2), w.dim(3), pass);
  }
  // y (B, O, h, w), weight (O, I, k, k).
  static double conv_flops(const Ref& y, const Ref& w) {
    return 2.0 * static_cast<double>(y.numel()) *
           static_cast<double>(w.dim(1) * w.dim(2) * w.dim(3));
  }
  // x (B, I, h, w), weight (I, O, 2, 2).
  static double transposed_flops(const Ref& x, const Ref& w) {
    return 2.0 * static_cast<double>(x.numel()) *
           static_cast<double>(w.dim(1) * w.dim(2) * w.dim(3));
  }
  // points (P, N, 10), weight (C, 10).
  static double linear_flops(const Ref& points, const Ref& w) {
    return 2.0 * static_cast<double>(points.numel()) * static_cast<double>(w.dim(0));
  }

  std::unique_ptr<Backend> inner_;
  std::map<std::string, OpTotal> totals_;
};

// ---- inputs ----

constexpr uint64_t kSimulatorSeed = 1;
constexpr double kGradClip = 10.0;
// Sparse ground truth coefficients per class id 0..12 (DESIGN.md section 3).
constexpr std::array<float, 13> kCoefficients = {0, 2, 8, 8, 8, 1, 1, 1, 1, 1, 1, 1, 1};

struct SizeSetup {
  std::string size;
  ModelConfig config;
  int batch = 1;
  ModelBatch inputs;                  // pillar_points (P, N, 10), pillar_cells (P, 3)
  Tensor<uint8_t> labels;             // (B, H, W)
  std::filesystem::path peer_inputs;  // the same arrays as raw files for the PyTorch peer
};

ModelConfig config_of(const std::string& size, bool transposed) {
  ModelConfig c;  // the paper's full size
  if (size == "small") {
    c.grid.cell = 0.2;
    c.pillar_channels = 16;
    c.base_width = 16;
  }
  c.transposed = transposed;
  return c;
}

// Sample b of a batch: simulated scan b of one street of `batch` scans, or the --scan file with
// its labels.
Scan input_scan(int b, int batch) {
  if (g_options.scan.empty()) {
    sim::SimScan simulated = sim::SequenceSimulator(kSimulatorSeed, batch).scan(b);
    Scan scan;
    scan.points = std::move(simulated.points);
    scan.labels = std::move(simulated.labels);
    return scan;
  }
  const std::filesystem::path labels = g_options.scan.parent_path().parent_path() / "labels" /
                                       g_options.scan.filename().replace_extension(".label");
  PS_CHECK(std::filesystem::exists(labels),
           "--scan={}: the training step needs its labels, expected in {}", g_options.scan.string(),
           labels.string());
  return read_scan(g_options.scan, labels);
}

// Scans 0..batch-1 -> all their non-empty pillars (inference subsampling to N points),
// decorated, in one batch; labels: each scan's sparse ground truth.
SizeSetup make_setup(const std::string& size) {
  SizeSetup s;
  s.size = size;
  s.config = config_of(size, false);
  s.batch = size == "small" ? 2 : 1;
  const GridSpec& grid = s.config.grid;
  const int N = s.config.max_points_per_pillar, H = grid.height(), W = grid.width();
  std::vector<float> points;
  std::vector<int32_t> cells;
  s.labels = Tensor<uint8_t>({s.batch, H, W});
  for (int b = 0; b < s.batch; ++b) {
    const Scan scan = input_scan(b, s.batch);
    const host::Pillars pillars =
        host::pillar_gather(scan.points, grid, {N, 0}, host::SampleMode::Inference, nullptr);
    const Tensor<float> decorated = host::decorate_points(scan.points, pillars, grid);
    points.insert(points.end(), decorated.data(), decorated.data() + decorated.numel());
    for (int64_t p = 0; p < pillars.num_pillars(); ++p) {
      cells.insert(cells.end(), {b, pillars.cell(p, 0), pillars.cell(p, 1)});
    }
    const Tensor<uint8_t> map = sparse_ground_truth(scan, ClassTable::defaults(), grid);
    std::copy(map.data(), map.data() + map.numel(), s.labels.data() + int64_t{b} * H * W);
  }
  const int64_t P = static_cast<int64_t>(cells.size() / 3);
  s.inputs.batch = s.batch;
  s.inputs.pillar_points = Tensor<float>({P, N, 10});
  std::copy(points.begin(), points.end(), s.inputs.pillar_points.data());
  s.inputs.pillar_cells = Tensor<int32_t>({P, 3});
  std::copy(cells.begin(), cells.end(), s.inputs.pillar_cells.data());

  s.peer_inputs = std::filesystem::temp_directory_path() /
                  fmt::format("pillarseg_bench_model_{}_{}", getpid(), size);
  const auto write = [&](const char* file, const auto& t) {
    write_file_atomic(s.peer_inputs / file, t.data(),
                      static_cast<size_t>(t.numel()) * sizeof(*t.data()));
  };
  write("points.f32", s.inputs.pillar_points);
  write("cells.i32", s.inputs.pillar_cells);
  write("labels.u8", s.labels);
  return s;
}

std::map<std::string, SizeSetup>& setups() {
  static std::map<std::string, SizeSetup> all;
  return all;
}

const SizeSetup& setup(const std::string& size) {
  auto it = setups().find(size);
  if (it == setups().end()) it = setups().emplace(size, make_setup(size)).first;
  return it->second;
}

void remove_peer_inputs() {
  for (const auto& [size, s] : setups()) std::filesystem::remove_all(s.peer_inputs);
}

// ---- the PyTorch peer ----

// "key=value key=value" after the first word of a PEER line -> map.
std::map<std::string, std::string> parse_fields(const std::string& line) {
  std::map<std::string, std::string> fields;
  std::istringstream in(line.substr(line.find(' ') + 1));
  std::string token;
  while (in >> token) {
    const size_t eq = token.find('=');
    if (eq != std::string::npos) fields[token.substr(0, eq)] = token.substr(eq + 1);
  }
  return fields;
}

// A running `pytorch_peer.py --serve`: each command written to its stdin is answered by one
// PEER_STEP line with the wall and CPU time of the step it ran. Everything else it prints
// (stderr merged) is kept: the final PEER line, PEER_PROFILE lines, error messages.
class PeerProcess {
 public:
  // Starts the peer with --threads T --serve `arguments` and waits until it has warmed up.
  explicit PeerProcess(const std::vector<std::string>& arguments) {
    std::vector<std::string> args{g_options.peer_python, g_options.peer_script.string(),
                                  "--threads", std::to_string(num_threads()), "--serve"};
    args.insert(args.end(), arguments.begin(), arguments.end());
    std::vector<char*> argv;
    for (std::string& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    int to_child[2], from_child[2];
    PS_CHECK(pipe2(to_child, O_CLOEXEC) == 0 && pipe2(from_child, O_CLOEXEC) == 0,
             "cannot create pipes for the PyTorch peer: {}", std::strerror(errno));
    posix_spawn_file_actions_t actions;
    posix_spawn_file_actions_init(&actions);
    posix_spawn_file_actions_adddup2(&actions, to_child[0], STDIN_FILENO);
    posix_spawn_file_actions_adddup2(&actions, from_child[1], STDOUT_FILENO);
    posix_spawn_file_actions_adddup2(&actions, from_child[1], STDERR_FILENO);
    const int error = posix_spawn(&pid_, argv[0], &actions, nullptr, argv.data(), environ);
    posix_spawn_file_actions_destroy(&actions);
    close(to_child[0]);
    close(from_child[1]);
    if (error != 0) {
      close(to_child[1]);
      close(from_child[0]);
      pid_ = -1;
      failure_ = fmt::format("skipped: cannot run {}: {}", args[0], std::strerror(error));
      return;
    }
    to_peer_ = fdopen(to_child[1], "w");
    from_peer_ = fdopen(from_child[0], "r");
    std::string ready;
    if (!read_until("PEER_READY", ready)) finish();  // it stopped: skipped (no torch) or failed
  }
  ~PeerProcess() { finish(); }
  PeerProcess(const PeerProcess&) = delete;
  PeerProcess& operator=(const PeerProcess&) = delete;

  bool ok() const { return failure_.empty(); }
  const std::string& failure() const { return failure_; }
  const std::string& summary() const { return summary_; }  // the final PEER line
  const std::vector<std::string>& lines() const { return lines_; }

  // Runs one command; returns its wall seconds and adds its times to `times`, or returns
  // nullopt once the peer has failed.
  std::optional<double> step(const std::string& command, StepTimes& times) {
    if (!ok() || pid_ < 0) return std::nullopt;
    std::string answer;
    const bool sent =
        std::fputs((command + "\n").c_str(), to_peer_) >= 0 && std::fflush(to_peer_) == 0;
    if (!sent || !read_until("PEER_STEP ", answer)) {
      finish();
      if (ok()) failure_ = fmt::format("the PyTorch peer stopped answering '{}'", command);
      return std::nullopt;
    }
    const auto fields = parse_fields(answer);
    times.add(std::stod(fields.at("wall_ms")) * 1e-3, std::stod(fields.at("cpu_ms")) * 1e-3);
    return times.wall.back();
  }

  // Closes the peer's stdin (it then prints its PEER line and exits) and waits for it.
  void finish() {
    if (pid_ < 0) return;
    std::fclose(to_peer_);
    std::string unused;
    read_until("", unused, /*to_end=*/true);
    std::fclose(from_peer_);
    int status = 0;
    waitpid(pid_, &status, 0);
    pid_ = -1;
    const int exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    for (const std::string& line : lines_) {
      if (line.rfind("PEER ", 0) == 0) summary_ = line;
    }
    if (summary_.rfind("PEER skipped", 0) == 0) {
      failure_ = summary_.substr(5);
    } else if (exit_code != 0 || summary_.empty()) {
      std::string output;
      for (const std::string& line : lines_) output += "\n    " + line;
      failure_ = fmt::format("the PyTorch peer failed (exit {}):{}", exit_code, output);
    }
  }

 private:
  // Reads lines into lines_ until one starts with `prefix` (returned in `line`, not kept);
  // false at the end of the output. to_end: read everything.
  bool read_until(const std::string& prefix, std::string& line, bool to_end = false) {
    std::array<char, 4096> buffer{};
    while (std::fgets(buffer.data(), static_cast<int>(buffer.size()), from_peer_) != nullptr) {
      line = buffer.data();
      if (!line.empty() && line.back() == '\n') line.pop_back();
      if (!to_end && line.rfind(prefix, 0) == 0) return true;
      lines_.push_back(line);
    }
    return false;
  }

  pid_t pid_ = -1;
  FILE* to_peer_ = nullptr;
  FILE* from_peer_ = nullptr;
  std::vector<std::string> lines_;
  std::string summary_, failure_;
};

// ---- results kept for the summary ----

struct CaseResult {
  double gflop = 0.0;
  int64_t params = 0, pillars = 0;
  StepTimes ours, torch;
  std::optional<double> ours_rss_mb, torch_rss_mb;
  std::map<std::string, OpTotal> ours_ops;  // mean per step
  std::string peer_note, peer_profile;
};

struct ModelCase {
  std::string size;
  bool transposed = false;
  bool training = false;
  std::string key() const {
    return fmt::format("{} {} {}", size, transposed ? "transposed" : "bilinear",
                       training ? "train" : "forward");
  }
};

std::map<std::string, CaseResult> g_cases;  // by ModelCase::key()
// A rate by the wall clock and by the process's CPU time (GFLOP per CPU-second: a thread's
// rate when it has a core to itself, which a shared machine's load changes less).
struct Rate {
  double wall_gflops = 0.0, cpu_gflops = 0.0;
};
std::map<int, Rate> g_gemm;  // by thread count
struct LayerResult {
  std::string name, shape;
  double gflop = 0.0;
  StepTimes ours, reference, torch;  // ours: the CPU backend's fast path; reference: host/
};
std::vector<LayerResult> g_layers;
std::string g_layer_peer_note;

void set_rate_counters(benchmark::State& state, double flops, const StepTimes& t) {
  state.counters["GFLOP"] = flops * 1e-9;
  state.counters["median_ms"] = t.wall_median() * 1e3;
  state.counters["GFLOP/s"] = flops * 1e-9 / t.wall_median();
  state.counters["cpu_ms"] = t.cpu_median() * 1e3;
  state.counters["GFLOP/cpu_s"] = flops * 1e-9 / t.cpu_median();
  state.counters["threads"] = num_threads();
}

// Adds PyTorch's median and the median per-step ratio ours / PyTorch to the counters.
void set_peer_counters(benchmark::State& state, const StepTimes& ours, const StepTimes& torch) {
  if (torch.wall.empty()) return;
  state.counters["torch_ms"] = torch.wall_median() * 1e3;
  state.counters["ours/torch"] = median_ratio(ours.wall, torch.wall);
  state.counters["ours/torch_cpu"] = median_ratio(ours.cpu, torch.cpu);
}

// ---- GEMM reference ----

constexpr int64_t kGemmSize = 4096;
// Work items of the threaded GEMM: blocks of rows of A (and C), each multiplied by all of B,
// scheduled dynamically. Measured here with 2 threads: 8 row blocks 174 GFLOP/s, 16 column
// blocks 140 (each column block packs all of A again).
constexpr int64_t kGemmRowBlocks = 8;

void BM_Gemm(benchmark::State& state, int threads) {
  using Matrix = Eigen::MatrixXf;
  const Matrix a = Matrix::Random(kGemmSize, kGemmSize);
  const Matrix b = Matrix::Random(kGemmSize, kGemmSize);
  Matrix c = Matrix::Zero(kGemmSize, kGemmSize);
  StepTimes t;
  for (auto _ : state) {
    state.SetIterationTime(time_once(t, [&] {
      if (threads == 1) {
        c.noalias() = a * b;
      } else {
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
        for (int64_t block = 0; block < kGemmRowBlocks; ++block) {
          const int64_t i0 = kGemmSize * block / kGemmRowBlocks;
          const int64_t i1 = kGemmSize * (block + 1) / kGemmRowBlocks;
          c.middleRows(i0, i1 - i0).noalias() = a.middleRows(i0, i1 - i0) * b;
        }
      }
      benchmark::DoNotOptimize(c.data());
    }));
  }
  const double flops =
      2.0 * static_cast<double>(kGemmSize * kGemmSize) * static_cast<double>(kGemmSize);
  set_rate_counters(state, flops, t);
  state.counters["threads"] = threads;
  g_gemm[threads] = {flops * 1e-9 / t.wall_median(), flops * 1e-9 / t.cpu_median()};
}

// ---- conv layers ----

TensorF random_tensor(const Shape& shape, uint64_t seed) {
  Rng rng(seed);
  TensorF t(shape);
  for (float& v : t) v = static_cast<float>(rng.uniform(-1.0, 1.0));
  return t;
}

// One peer process for all conv layers (started by the first, finished before the models).
std::optional<PeerProcess>& conv_peer() {
  static std::optional<PeerProcess> peer;
  return peer;
}

void finish_conv_peer() {
  std::optional<PeerProcess>& peer = conv_peer();
  if (!peer) return;
  peer->finish();
  if (!peer->ok()) g_layer_peer_note = peer->failure();
  peer.reset();
}

// Ours (the CPU backend's 3x3 convolution: Winograd, bias in its epilogue), the host/ reference
// and PyTorch's nn.Conv2d at one layer shape, alternating ours and PyTorch.
void BM_Conv3x3(benchmark::State& state, const Layer& l) {
  const TensorF x = random_tensor({l.batch, l.in, l.h, l.w}, 1);
  TensorF w = random_tensor({l.out, l.in, 3, 3}, 2);
  TensorF bias = random_tensor({l.out}, 3);
  TensorF y({l.batch, l.out, l.h, l.w});  // zero-filled: its pages are touched before timing
  TensorF y_reference({l.batch, l.out, l.h, l.w});
  const std::unique_ptr<Backend> backend = make_cpu_backend();
  const Ref x_ref{const_cast<float*>(x.data()), x.shape()}, w_ref{w.data(), w.shape()},
      bias_ref{bias.data(), bias.shape()};
  Ref y_ref{y.data(), y.shape()};
  if (g_options.peer && !conv_peer() && g_layer_peer_note.empty()) {
    conv_peer().emplace(std::vector<std::string>{"--case", "conv3x3"});
  }
  PeerProcess* peer = conv_peer() && conv_peer()->ok() ? &*conv_peer() : nullptr;
  const std::string command = fmt::format("conv3x3 {}:{}:{}:{}", l.in, l.out, l.h, l.w);
  LayerResult r{
      l.name, fmt::format("{} -> {} @ {}x{}", l.in, l.out, l.h, l.w), l.flops() * 1e-9, {}, {}, {}};
  int64_t pair = 0;
  for (auto _ : state) {
    // The order alternates so that a load rising or falling through the run weighs on both.
    const bool ours_first = pair++ % 2 == 0;
    if (peer && !ours_first) peer->step(command, r.torch);
    state.SetIterationTime(time_once(r.ours, [&] {
      backend->conv2d_forward(x_ref, w_ref, &bias_ref, 1, y_ref);
      benchmark::DoNotOptimize(y.data());
    }));
    if (peer && ours_first) peer->step(command, r.torch);
    time_once(r.reference, [&] {
      host::conv2d_forward(x, w, &bias, 1, y_reference);
      benchmark::DoNotOptimize(y_reference.data());
    });
  }
  if (peer && !peer->ok()) finish_conv_peer();
  set_rate_counters(state, l.flops(), r.ours);
  set_peer_counters(state, r.ours, r.torch);
  g_layers.push_back(std::move(r));
}

// The 3x3 conv layers of the full-size U-Nets, bilinear first, then the transposed variant's
// shapes that the bilinear one does not have; x (1, I, h, w) -> (1, O, h, w).
std::vector<Layer> conv3x3_layers() {
  std::vector<Layer> all;
  for (bool transposed : {false, true}) {
    auto backend = make_cpu_backend();
    const PillarSegNet net(config_of("full", transposed), *backend);
    for (Layer l : forward_layers(net, 1, 0)) {
      if (l.kind != Layer::Kind::Conv || l.k != 3) continue;
      const bool seen = std::any_of(all.begin(), all.end(), [&](const Layer& o) {
        return o.in == l.in && o.out == l.out && o.h == l.h && o.w == l.w;
      });
      if (seen) continue;
      l.name = (transposed ? "T:" : "") +
               l.name.substr(l.name.find('.') + 1);  // drop segmentation_head.
      all.push_back(l);
    }
  }
  return all;
}

// ---- the model ----

// One step: eval forward, or training forward + loss + backward + clip + Adam.
void model_step(PillarSegNet& net, Backend& backend, const SizeSetup& s, bool training,
                int64_t& adam_steps) {
  if (!training) {
    net.forward(s.inputs, false);
    return;
  }
  net.forward(s.inputs, true);
  net.loss(s.labels, LossKind::CrossEntropy, kCoefficients);
  net.backward();
  ParameterSet& ps = net.parameters();
  Ref grads = ps.grads();
  const double norm = std::sqrt(backend.sum_of_squares(grads));
  if (norm > kGradClip) backend.scale(grads, static_cast<float>(kGradClip / (norm + 1e-6)));
  AdamHyper hyper;
  hyper.step = ++adam_steps;
  Ref values = ps.values(), m = ps.adam_m(), v = ps.adam_v();
  backend.adam_step(values, grads, m, v, hyper);
}

std::vector<std::string> peer_model_arguments(const ModelCase& c, const SizeSetup& s) {
  const ModelConfig config = config_of(c.size, c.transposed);
  std::vector<std::string> args{"--case",
                                c.training ? "train" : "forward",
                                "--variant",
                                c.transposed ? "transposed" : "bilinear",
                                "--batch",
                                std::to_string(s.batch),
                                "--height",
                                std::to_string(config.grid.height()),
                                "--width",
                                std::to_string(config.grid.width()),
                                "--pillar-channels",
                                std::to_string(config.pillar_channels),
                                "--base-width",
                                std::to_string(config.base_width),
                                "--depth",
                                std::to_string(config.depth),
                                "--points-per-pillar",
                                std::to_string(config.max_points_per_pillar),
                                "--inputs",
                                s.peer_inputs.string()};
  if (g_options.peer_profile) args.push_back("--profile");
  return args;
}

// Ours and PyTorch (its own process, warmed up first), one step each in turn.
void BM_Model(benchmark::State& state, const ModelCase& c) {
  finish_conv_peer();
  const SizeSetup& s = setup(c.size);
  CaseResult& r = g_cases[c.key()];
  std::optional<PeerProcess> peer;
  if (g_options.peer) peer.emplace(peer_model_arguments(c, s));
  const bool rss_reset = reset_peak_rss();
  TimedBackend backend(make_cpu_backend());
  PillarSegNet net(config_of(c.size, c.transposed), backend, /*seed=*/1);
  const double step_flops =
      (c.training ? 3.0 : 1.0) *
      total_flops(forward_layers(net, s.batch, s.inputs.pillar_points.dim(0)));
  int64_t adam_steps = 0;
  model_step(net, backend, s, c.training,
             adam_steps);  // warm-up: plans and first-touches the arenas
  backend.clear_totals();
  int64_t pair = 0;
  for (auto _ : state) {
    // The order alternates so that a load rising or falling through the run weighs on both.
    const bool ours_first = pair++ % 2 == 0;
    if (peer && !ours_first) peer->step("step", r.torch);
    state.SetIterationTime(
        time_once(r.ours, [&] { model_step(net, backend, s, c.training, adam_steps); }));
    if (peer && ours_first) peer->step("step", r.torch);
  }
  const double rss = peak_rss_mb();
  r.gflop = step_flops * 1e-9;
  r.params = net.parameters().num_trainable();
  r.pillars = s.inputs.pillar_points.dim(0);
  if (rss_reset) r.ours_rss_mb = rss;
  const double steps = static_cast<double>(r.ours.wall.size());
  for (auto [op, total] : backend.totals()) {
    total.seconds /= steps, total.flops /= steps;
    total.calls = static_cast<int64_t>(static_cast<double>(total.calls) / steps);
    r.ours_ops[op] = total;
  }
  set_rate_counters(state, step_flops, r.ours);
  state.counters["peak_RSS_MB"] = rss;
  state.counters["pillars"] = static_cast<double>(r.pillars);
  if (!peer) return;
  peer->finish();
  if (!peer->ok()) {
    r.peer_note = peer->failure();
    return;
  }
  set_peer_counters(state, r.ours, r.torch);
  const auto fields = parse_fields(peer->summary());
  r.torch_rss_mb = std::stod(fields.at("peak_rss_mb"));
  for (const std::string& line : peer->lines()) {
    if (line.rfind("PEER_PROFILE ", 0) == 0) r.peer_profile += "  " + line.substr(13) + "\n";
  }
  // The same network and input on both sides: parameter and FLOP counts must agree.
  const int64_t peer_params = std::stoll(fields.at("params"));
  const double peer_gflop = std::stod(fields.at("gflop"));
  if (peer_params != r.params || std::abs(peer_gflop - r.gflop) > 0.01 * r.gflop) {
    r.peer_note =
        fmt::format("MISMATCH: PyTorch has {} parameters and {:.2f} GFLOP, ours {} and {:.2f}",
                    peer_params, peer_gflop, r.params, r.gflop);
  }
}

// ---- summary ----

std::string fixed(const std::optional<double>& v, int decimals) {
  return v ? fmt::format("{:.{}f}", *v, decimals) : std::string("-");
}

std::optional<double> wall_ms(const StepTimes& t) {
  return t.wall.empty() ? std::nullopt : std::optional<double>(t.wall_median() * 1e3);
}

std::optional<double> cpu_ms(const StepTimes& t) {
  return t.cpu.empty() ? std::nullopt : std::optional<double>(t.cpu_median() * 1e3);
}

std::string wall_list(const StepTimes& t) {
  std::string s;
  for (double v : t.wall) s += fmt::format("{}{:.0f}", s.empty() ? "" : ",", v * 1e3);
  return s.empty() ? std::string("-") : s;
}

std::string ratio(const std::vector<double>& ours, const std::vector<double>& torch) {
  return ours.empty() || torch.empty() ? std::string("-")
                                       : fmt::format("{:.2f}", median_ratio(ours, torch));
}

void print_gemm_and_layers() {
  if (!g_gemm.empty()) {
    fmt::print("\nGEMM 4096^3 fp32 (Eigen), GFLOP/s by the wall clock and GFLOP per CPU-second:\n");
    for (const auto& [threads, rate] : g_gemm) {
      fmt::print("  {} thread(s): {:.1f} GFLOP/s, {:.1f} GFLOP/cpu-s\n", threads, rate.wall_gflops,
                 rate.cpu_gflops);
    }
  }
  if (g_layers.empty()) return;
  const auto gemm = g_gemm.find(num_threads());
  const auto share = [&](double rate, bool by_cpu) {
    if (gemm == g_gemm.end()) return std::string("-");
    const double gemm_rate = by_cpu ? gemm->second.cpu_gflops : gemm->second.wall_gflops;
    return fmt::format("{:.0f}%", 100.0 * rate / gemm_rate);
  };
  fmt::print(
      "\n3x3 conv layers, the CPU backend's conv2d_forward (Winograd F(4x4,3x3)), batch 1, {} "
      "threads, median of {}: ms, GFLOP/s, CPU ms, GFLOP per CPU-s, % of the {}-thread GEMM's "
      "rate by wall and by CPU time (GFLOP: the direct convolution's 2 O I 9 h w, so Winograd's "
      "fewer multiplies show as a higher rate); the host/ reference (im2col + GEMM) ms; PyTorch's "
      "nn.Conv2d run in turn, and the median step ratio ours / torch (wall, CPU):\n",
      num_threads(), g_options.layer_reps, num_threads());
  fmt::print(
      "  {:<30} {:>22} {:>7} {:>7} {:>7} {:>8} {:>6} {:>6} | {:>7} | {:>8} {:>7} | {:>5} {:>5}\n",
      "layer", "I -> O @ h x w", "ms", "GFLOP/s", "CPU ms", "GF/cpu-s", "%wall", "%CPU", "ref ms",
      "torch ms", "CPU ms", "wall", "CPU");
  for (const LayerResult& l : g_layers) {
    const double wall_rate = l.gflop / l.ours.wall_median(),
                 cpu_rate = l.gflop / l.ours.cpu_median();
    fmt::print(
        "  {:<30} {:>22} {:>7.0f} {:>7.1f} {:>7.0f} {:>8.1f} {:>6} {:>6} | {:>7.0f} | {:>8} {:>7} "
        "| {:>5} {:>5}\n",
        l.name, l.shape, l.ours.wall_median() * 1e3, wall_rate, l.ours.cpu_median() * 1e3, cpu_rate,
        share(wall_rate, false), share(cpu_rate, true), l.reference.wall_median() * 1e3,
        fixed(wall_ms(l.torch), 0),
        fixed(cpu_ms(l.torch), 0), ratio(l.ours.wall, l.torch.wall),
        ratio(l.ours.cpu, l.torch.cpu));
  }
  if (!g_layer_peer_note.empty()) fmt::print("  PyTorch: {}\n", g_layer_peer_note);
}

void print_cases() {
  if (g_cases.empty()) return;
  fmt::print(
      "\nPillarSegNet on the CPU, {} threads, ours and PyTorch one step each in turn, median of {} "
      "after one warm-up: wall ms, GFLOP/s, process CPU ms (all threads), peak RSS MB; the median "
      "step ratio ours / torch (> 1: ours slower) by wall and by CPU time:\n",
      num_threads(), g_options.reps);
  fmt::print(
      "  {:<26} {:>7} {:>7} | {:>8} {:>7} {:>7} {:>7} | {:>8} {:>7} {:>7} {:>7} | {:>5} {:>5}\n",
      "case", "pillars", "GFLOP", "ours ms", "GFLOP/s", "CPU ms", "RSS MB", "torch ms", "GFLOP/s",
      "CPU ms", "RSS MB", "wall", "CPU");
  for (const auto& [key, r] : g_cases) {
    const auto rate = [&](const StepTimes& t) {
      return t.wall.empty() ? std::string("-") : fmt::format("{:.1f}", r.gflop / t.wall_median());
    };
    fmt::print(
        "  {:<26} {:>7} {:>7.1f} | {:>8} {:>7} {:>7} {:>7} | {:>8} {:>7} {:>7} {:>7} | {:>5} "
        "{:>5}\n",
        key, r.pillars, r.gflop, fixed(wall_ms(r.ours), 0), rate(r.ours), fixed(cpu_ms(r.ours), 0),
        fixed(r.ours_rss_mb, 0), fixed(wall_ms(r.torch), 0), rate(r.torch),
        fixed(cpu_ms(r.torch), 0), fixed(r.torch_rss_mb, 0), ratio(r.ours.wall, r.torch.wall),
        ratio(r.ours.cpu, r.torch.cpu));
    fmt::print("  {:<26} wall ms of each step: ours {}  torch {}\n", "", wall_list(r.ours),
               wall_list(r.torch));
    if (!r.peer_note.empty()) fmt::print("  {:<26} {}\n", "", r.peer_note);
  }
  for (const auto& [key, r] : g_cases) {
    if (r.ours_ops.empty()) continue;
    const double mean_ms = 1e3 * std::accumulate(r.ours.wall.begin(), r.ours.wall.end(), 0.0) /
                           static_cast<double>(r.ours.wall.size());
    fmt::print("\nWhere our time goes: {} (mean of the timed steps: {:.0f} ms)\n", key, mean_ms);
    fmt::print("  {:<30} {:>7} {:>10} {:>7} {:>9}\n", "backend op", "calls", "ms/step", "share",
               "GFLOP/s");
    std::vector<std::pair<std::string, OpTotal>> ops(r.ours_ops.begin(), r.ours_ops.end());
    std::sort(ops.begin(), ops.end(),
              [](const auto& a, const auto& b) { return a.second.seconds > b.second.seconds; });
    double accounted_ms = 0.0;
    for (const auto& [op, t] : ops) {
      accounted_ms += t.seconds * 1e3;
      const std::string op_rate =
          t.flops > 0 ? fmt::format("{:.1f}", t.flops * 1e-9 / t.seconds) : "";
      fmt::print("  {:<30} {:>7} {:>10.1f} {:>6.1f}% {:>9}\n", op, t.calls, t.seconds * 1e3,
                 100.0 * t.seconds * 1e3 / mean_ms, op_rate);
    }
    fmt::print("  {:<30} {:>7} {:>10.1f}\n", "(the model's own code)", "", mean_ms - accounted_ms);
  }
  for (const auto& [key, r] : g_cases) {
    if (r.peer_profile.empty()) continue;
    fmt::print("\nWhere PyTorch's time goes: {} (one more step, torch.profiler)\n{}", key,
               r.peer_profile);
  }
}

// ---- registration ----

void register_benchmarks() {
  const int threads = num_threads();
  for (int t : threads == 1 ? std::vector<int>{1} : std::vector<int>{1, threads}) {
    benchmark::RegisterBenchmark(fmt::format("Gemm/{}/threads:{}", kGemmSize, t).c_str(), BM_Gemm,
                                 t)
        ->Iterations(g_options.layer_reps)
        ->UseManualTime()
        ->Unit(benchmark::kMillisecond);
  }
  for (const Layer& l : conv3x3_layers()) {
    benchmark::RegisterBenchmark(
        fmt::format("Conv3x3/{}/{}to{}/{}x{}", l.name, l.in, l.out, l.h, l.w).c_str(), BM_Conv3x3,
        l)
        ->Iterations(g_options.layer_reps)
        ->UseManualTime()
        ->Unit(benchmark::kMillisecond);
  }
  std::vector<std::string> sizes{"full"};
  if (g_options.small) sizes.insert(sizes.begin(), "small");
  for (const std::string& size : sizes) {
    for (bool transposed : {false, true}) {
      for (bool training : {false, true}) {
        const ModelCase c{size, transposed, training};
        benchmark::RegisterBenchmark(
            fmt::format("Model/{}/{}/{}", size, transposed ? "transposed" : "bilinear",
                        training ? "train" : "forward")
                .c_str(),
            BM_Model, c)
            ->Iterations(g_options.reps)
            ->UseManualTime()
            ->Unit(benchmark::kMillisecond);
      }
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  // A peer that dies while we write to it must show up as an error, not kill this process.
  std::signal(SIGPIPE, SIG_IGN);
  try {
    g_options = parse_options(argc, argv);
    set_num_threads(g_options.threads);
    benchmark::Initialize(&argc, argv);
    if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
    register_benchmarks();
    benchmark::RunSpecifiedBenchmarks();
    finish_conv_peer();
    print_gemm_and_layers();
    print_cases();
    remove_peer_inputs();
    benchmark::Shutdown();
  } catch (const std::exception& e) {
    remove_peer_inputs();
    std::fprintf(stderr, "bench_model: %s\n", e.what());
    return 1;
  }
  return 0;
}
