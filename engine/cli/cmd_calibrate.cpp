// pillarseg calibrate: the INT8 scales of a checkpoint (DESIGN.md section 10,
// engine/model/calibration.hpp) from FP32 evaluation forwards over N scans of a data set, written
// with every tensor of the checkpoint into a new safetensors file (which still loads as FP32).
#include <fmt/format.h>

#include <algorithm>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "engine/cli/cli_util.hpp"
#include "engine/cli/commands.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/model/calibration.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/model_graph.hpp"
#include "engine/pipeline/segmenter.hpp"
#include "engine/util/progress.hpp"

namespace pillarseg::cli {

namespace {

struct CalibrateArgs {
  std::string data, weights, out, config;
  std::vector<int> sequences;
  int scans = 32;
  double percentile = kCalibrationPercentile;
};

void run_calibrate(const CalibrateArgs& a) {
  PS_CHECK(a.out != a.weights, "calibrate: --out must be another file than --weights ({})", a.weights);
  const Checkpoint ckpt = read_checkpoint(a.weights);
  const RunConfig config = config_for(ckpt, a.config);
  ScanSegmenter segmenter(config.model, make_cpu_backend());
  PillarSegNet& net = segmenter.net();
  load_weights(ckpt, net, false);
  // The scans: every k-th of the sequences' (default: the config's training split), N in all.
  const std::vector<int> ids = a.sequences.empty() ? config.train.sequences : a.sequences;
  PS_CHECK(!ids.empty(), "calibrate: no sequences (give --sequences)");
  std::vector<std::pair<std::shared_ptr<Sequence>, size_t>> scans;
  for (const int id : ids) {
    auto seq = std::make_shared<Sequence>(a.data, id, config.input);
    for (size_t i = 0; i < seq->size(); ++i) scans.emplace_back(seq, i);
  }
  PS_CHECK(!scans.empty(), "calibrate: sequences {} of {} hold no scans", fmt::join(ids, ", "), a.data);
  const size_t n = std::min(scans.size(), static_cast<size_t>(a.scans));
  InputScaleCalibrator calibrator(a.percentile);
  {
    const CalibrationScope observing(net, calibrator);
    Progress progress("calibrate", static_cast<int64_t>(n), "scans");
    std::vector<uint8_t> labels(static_cast<size_t>(config.model.grid.cells()));
    for (size_t k = 0; k < n; ++k) {
      const auto& [seq, i] = scans[k * scans.size() / n];
      const Scan scan = seq->load(i);
      segmenter.segment_mapped(scan.points, labels.data());
      progress.update(static_cast<int64_t>(k + 1));
    }
    progress.finish();
  }
  const std::map<std::string, Int8Input> inputs = calibrator.inputs();
  std::vector<std::string> keys;
  for (const auto& [key, input] : inputs) keys.push_back(key);
  const auto weight_scales = int8_weight_scales(net.parameters(), keys);
  weights::SafeTensors file;
  for (const std::string& name : ckpt.file.names())
    if (name.rfind(kQuantizationPrefix, 0) != 0) file.add(ckpt.file.at(name));
  file.metadata = ckpt.file.metadata;
  int64_t non_negative = 0, winograd = 0;
  for (const auto& [key, input] : inputs) {
    if (input.has_winograd()) {
      Tensor<float> positions({16});
      std::copy(input.winograd.begin(), input.winograd.end(), positions.data());
      file.add_f32(winograd_input_scale_name(key), positions);
      ++winograd;
    }
    Tensor<float> scale({1}), unsigned_range({1});
    scale.data()[0] = input.scale;
    unsigned_range.data()[0] = input.non_negative ? 1.0f : 0.0f;
    non_negative += input.non_negative;
    file.add_f32(input_scale_name(key), scale);
    file.add_f32(input_non_negative_name(key), unsigned_range);
    const std::vector<float>& ws = weight_scales.at(key);
    Tensor<float> w({static_cast<int64_t>(ws.size())});
    std::copy(ws.begin(), ws.end(), w.data());
    file.add_f32(weight_scale_name(key), w);
  }
  file.metadata["quantization"] =
      fmt::format("int8: per-tensor input scales (the {}th percentile of |x| over {} scans of sequences {}, "
                  "largest / 255 for an input never negative, else / 127), for the 3x3 pad-1 convolutions also "
                  "per-position Winograd F(2x2, 3x3) input scales (the same percentile of |V_p|, largest / 127), "
                  "per-output-channel weight scales (max |w| / 127, BatchNorm folded)",
                  a.percentile, n, fmt::join(ids, ", "));
  file.write(a.out);
  const auto by_scale = [](const auto& x, const auto& y) { return x.second.scale < y.second.scale; };
  fmt::print("calibrated {} convolutions on {} scans ({}th percentile of |x|; {} inputs never negative, "
             "quantized to 0..255; {} with Winograd-domain scales); input scales {:.3g} to {:.3g}\n",
             inputs.size(), n, a.percentile, non_negative, winograd,
             std::min_element(inputs.begin(), inputs.end(), by_scale)->second.scale,
             std::max_element(inputs.begin(), inputs.end(), by_scale)->second.scale);
  fmt::print("wrote {} (loads as FP32 anywhere; --precision int8 uses the scales)\n", a.out);
}

}  // namespace

void add_calibrate(CLI::App& app) {
  auto a = std::make_shared<CalibrateArgs>();
  CLI::App* cmd = app.add_subcommand(
      "calibrate", "INT8 scales of a checkpoint from FP32 forwards over scans of a data set (--precision int8)");
  cmd->add_option("--data", a->data, "SemanticKITTI-layout root (sequences/)")->required();
  cmd->add_option("--weights", a->weights, "the FP32 checkpoint (.safetensors)")->required()->check(CLI::ExistingFile);
  cmd->add_option("--out", a->out, "the calibrated checkpoint to write (.safetensors)")->required();
  cmd->add_option("--config", a->config, "run config (default: the checkpoint's)");
  cmd->add_option("--sequences", a->sequences, "sequences to draw scans from (default: the config's training split)");
  cmd->add_option("--scans", a->scans, "scans to calibrate on, spread evenly over the sequences")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--percentile", a->percentile, "the percentile of |x| a convolution's input scale keeps")
      ->check(CLI::Range(50.0, 100.0));
  cmd->callback([a] { run_calibrate(*a); });
}

}  // namespace pillarseg::cli
