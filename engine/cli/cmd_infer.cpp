// pillarseg infer / render: one scan through a trained model (label map PNG, class ids,
// probabilities), and the paper's Fig. 3 panels (points, observability, prediction, ground
// truth) for a scan of a sequence.
#include <fmt/format.h>

#include "core/io.hpp"
#include "engine/cli/cli_util.hpp"
#include "engine/cli/commands.hpp"
#include "engine/eval/evaluate.hpp"
#include "engine/render/label_map.hpp"
#include "engine/render/render.hpp"
#include "engine/train/checkpoint.hpp"
#include "host/raywalk.hpp"
#include "weights_io/half.hpp"

namespace pillarseg::cli {

namespace {

struct InferArgs {
  std::string weights, scan, out, config, device = "cpu", conv = "own";
  bool probabilities = false, mask_unobserved = false;
};

struct RenderArgs {
  std::string data, weights, config, out, mode = "sparse", device = "cpu", conv = "own", cache;
  int sequence = -1, scan = -1;
  bool mask_unobserved = false;
};

struct LoadedModel {
  std::unique_ptr<Backend> backend;
  std::unique_ptr<PillarSegNet> net;
  RunConfig config;
};

LoadedModel load_model(const std::string& weights, const std::string& config, const std::string& device,
                       const std::string& conv) {
  const Checkpoint ckpt = read_checkpoint(weights);
  LoadedModel m;
  m.config = config_for(ckpt, config);
  m.backend = make_backend(device, conv);
  m.net = std::make_unique<PillarSegNet>(m.config.model, *m.backend);
  load_weights(ckpt, *m.net, false);
  return m;
}

Tensor<uint8_t> observed_mask(const Tensor<uint32_t>& observability) {
  Tensor<uint8_t> mask(observability.shape());
  for (int64_t i = 0; i < mask.numel(); ++i) mask[i] = observability[i] > 0;
  return mask;
}

void run_infer(const InferArgs& a) {
  LoadedModel m = load_model(a.weights, a.config, a.device, a.conv);
  const Scan scan = read_scan(a.scan);
  Prediction p = predict_scan(*m.net, m.config.model, scan.points, a.probabilities, a.mask_unobserved);
  if (a.mask_unobserved) {
    for (int64_t i = 0; i < p.labels.numel(); ++i)
      if (p.observability[i] == 0) p.labels[i] = 0;
  }
  const ClassTable classes = ClassTable::defaults();
  const std::string prefix = a.out;
  write_label_map(prefix + ".png", p.labels, classes);
  write_label_map(prefix + ".u8", p.labels, classes);
  std::string written = prefix + ".png, " + prefix + ".u8";
  if (a.probabilities) {
    std::vector<uint16_t> half(static_cast<size_t>(p.probabilities.numel()));
    const int64_t plane = p.labels.numel();
    for (int64_t i = 0; i < p.probabilities.numel(); ++i) {
      const bool masked = a.mask_unobserved && p.observability[i % plane] == 0;
      half[static_cast<size_t>(i)] = weights::float_to_f16_bits(masked ? 0.0f : p.probabilities[i]);
    }
    write_file_atomic(prefix + ".f16", half.data(), half.size() * sizeof(uint16_t));
    written += ", " + prefix + ".f16 (12 x H x W float16)";
  }
  fmt::print("{}: {} points -> {}\n", a.scan, scan.points.size(), written);
}

void run_render(const RenderArgs& a) {
  require_extension(a.out, {".png"}, "--out");
  const Sequence seq(a.data, a.sequence);
  const size_t index = scan_index(seq, a.scan);
  const Scan scan = seq.load(index);
  const ClassTable classes = ClassTable::defaults();
  GridSpec grid;
  std::optional<LoadedModel> model;
  if (!a.weights.empty()) {
    model = load_model(a.weights, a.config, a.device, a.conv);
    grid = model->config.model.grid;
  }
  std::vector<ImageRgb> panels;
  panels.push_back(render_points(scan.points, scan.labels, classes, grid));
  const Tensor<uint32_t> observability =
      host::observability_map(host::observability_2d(scan.points, Eigen::Vector3d::Zero(), grid));
  panels.push_back(render_observability(observability));
  const Tensor<uint8_t> mask = observed_mask(observability);
  if (model) {
    const Prediction p = predict_scan(*model->net, model->config.model, scan.points, false, false);
    ImageRgb prediction = render_label_map(p.labels, classes);
    if (a.mask_unobserved) apply_mask(prediction, mask);
    panels.push_back(std::move(prediction));
  }
  if (seq.has_labels(index)) {
    GroundTruthSettings settings;
    settings.grid = grid;
    std::optional<Cache> cache;
    if (!a.cache.empty()) cache.emplace(a.cache);
    const GroundTruthBuilder builder(seq, classes, settings, cache);
    ImageRgb truth = render_label_map(builder.map(index, parse_ground_truth_kind(a.mode)), classes);
    if (a.mask_unobserved) apply_mask(truth, mask);
    panels.push_back(std::move(truth));
  }
  write_png_rgb(a.out, stack_panels(panels));
  fmt::print("{}: panels (top to bottom) points, observability{}{} -> {}\n", seq.bin_path(index).string(),
             model ? ", prediction" : "", seq.has_labels(index) ? ", " + a.mode + " ground truth" : "", a.out);
}

}  // namespace

void add_infer(CLI::App& app) {
  auto a = std::make_shared<InferArgs>();
  CLI::App* cmd = app.add_subcommand("infer", "One scan -> PREFIX.png (colors), PREFIX.u8 (class ids, H x W)");
  cmd->add_option("--weights", a->weights, "checkpoint (.safetensors)")->required();
  cmd->add_option("--scan", a->scan, "scan file (.bin)")->required();
  cmd->add_option("--out", a->out, "output prefix")->required();
  cmd->add_flag("--probabilities", a->probabilities, "also PREFIX.f16: softmax probabilities, 12 x H x W float16");
  cmd->add_flag("--mask-unobserved", a->mask_unobserved, "label cells no ray observed as 0 (unlabeled)");
  cmd->add_option("--config", a->config, "run config (default: the one stored in the checkpoint)");
  cmd->add_option("--device", a->device, "cpu or cuda")->check(CLI::IsMember({"cpu", "cuda"}));
  cmd->add_option("--conv", a->conv, "Conv2d with --device cuda: own (our kernels), cudnn or cublas (for comparison)")->check(CLI::IsMember({"own", "cudnn", "cublas"}));
  cmd->callback([a] { run_infer(*a); });

  auto r = std::make_shared<RenderArgs>();
  CLI::App* rc = app.add_subcommand("render", "PNG panels like the paper's Fig. 3: points, observability, "
                                              "prediction (with --weights), ground truth");
  rc->add_option("--data", r->data, "SemanticKITTI root")->required();
  rc->add_option("--sequence", r->sequence, "sequence number")->required();
  rc->add_option("--scan", r->scan, "scan (frame) number")->required();
  rc->add_option("--out", r->out, "output .png")->required();
  rc->add_option("--weights", r->weights, "checkpoint for the prediction panel");
  rc->add_option("--config", r->config, "run config (default: the one stored in the checkpoint)");
  rc->add_option("--mode", r->mode, "ground truth: sparse or dense")->check(CLI::IsMember({"sparse", "dense"}));
  rc->add_flag("--mask-unobserved", r->mask_unobserved, "black out cells no ray observed");
  rc->add_option("--device", r->device, "cpu or cuda")->check(CLI::IsMember({"cpu", "cuda"}));
  rc->add_option("--conv", r->conv, "Conv2d with --device cuda: own (our kernels), cudnn or cublas (for comparison)")->check(CLI::IsMember({"own", "cudnn", "cublas"}));
  rc->add_option("--cache", r->cache, "ground-truth cache directory");
  rc->callback([r] { run_render(*r); });
}

}  // namespace pillarseg::cli
