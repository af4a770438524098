#include "engine/model/checkpoint.hpp"

#include <fmt/format.h>

#include <charconv>
#include <cstdlib>
#include <map>
#include <set>

#include "core/error.hpp"
#include "engine/model/architecture.hpp"
#include "engine/model/calibration.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

namespace {
constexpr const char* kFormat = "pillarseg-checkpoint-1";

int64_t parse_int(const std::string& text, const std::string& what, const fs::path& path) {
  int64_t v = 0;
  const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
  PS_CHECK(ec == std::errc() && ptr == text.data() + text.size(), "{}: metadata {} is not an integer: '{}'",
           path.string(), what, text);
  return v;
}
}  // namespace

void save_checkpoint(const fs::path& path, const PillarSegNet& net, const RunConfig& config, const TrainState& state,
                     bool with_optimizer) {
  const ParameterSet& ps = net.parameters();
  weights::SafeTensors file;
  for (size_t i = 0; i < ps.entries().size(); ++i) file.add_f32(ps.entries()[i].name, ps.download(static_cast<int>(i)));
  for (const auto& [name, count] : ps.counters()) file.add_i64(name, {}, {count});
  if (with_optimizer) {
    Tensor<float> m({ps.num_trainable()}), v({ps.num_trainable()});
    const auto hm = ps.download_adam_m(), hv = ps.download_adam_v();
    std::copy(hm.begin(), hm.end(), m.begin());
    std::copy(hv.begin(), hv.end(), v.begin());
    file.add_f32("optimizer.exp_avg", m);
    file.add_f32("optimizer.exp_avg_sq", v);
    if (!state.average_sum.empty()) {
      PS_CHECK(static_cast<int64_t>(state.average_sum.size()) == ps.num_trainable(),
               "{}: the weight average holds {} values, the model {}", path.string(),
               state.average_sum.size(), ps.num_trainable());
      Tensor<float> sum({ps.num_trainable()});
      std::copy(state.average_sum.begin(), state.average_sum.end(), sum.begin());
      file.add_f32(kAverageSumName, sum);
    }
  }
  file.metadata["format"] = kFormat;
  file.metadata["config"] = config.text;
  file.metadata["epoch"] = std::to_string(state.epoch);
  file.metadata["step"] = std::to_string(state.step);
  if (state.best_miou >= 0) {
    file.metadata["best_miou"] = fmt::format("{:.17g}", state.best_miou);
    file.metadata["best_epoch"] = std::to_string(state.best_epoch);
  }
  file.write(path);
}

Checkpoint read_checkpoint(const fs::path& path) {
  PS_CHECK(fs::exists(path), "--weights {}: no such file", path.string());
  Checkpoint c;
  c.file = weights::SafeTensors::read(path);
  const auto& md = c.file.metadata;
  if (auto it = md.find("config"); it != md.end()) c.config = parse_run_config(it->second, path.string() + " (config)");
  if (auto it = md.find("epoch"); it != md.end()) c.state.epoch = parse_int(it->second, "epoch", path);
  if (auto it = md.find("step"); it != md.end()) c.state.step = parse_int(it->second, "step", path);
  if (auto it = md.find("best_miou"); it != md.end()) {
    char* end = nullptr;
    c.state.best_miou = std::strtod(it->second.c_str(), &end);
    PS_CHECK(end != it->second.c_str() && *end == '\0' && c.state.best_miou >= 0 && c.state.best_miou <= 1,
             "{}: metadata best_miou is not an mIoU in [0, 1]: '{}'", path.string(), it->second);
  }
  if (auto it = md.find("best_epoch"); it != md.end()) c.state.best_epoch = parse_int(it->second, "best_epoch", path);
  c.has_optimizer = c.file.contains("optimizer.exp_avg") && c.file.contains("optimizer.exp_avg_sq");
  if (c.file.contains(kAverageSumName)) {
    const Tensor<float> sum = c.file.get_f32(kAverageSumName);
    c.state.average_sum.assign(sum.begin(), sum.end());
  }
  return c;
}

void load_weights(const Checkpoint& checkpoint, PillarSegNet& net, bool with_optimizer) {
  ParameterSet& ps = net.parameters();
  const weights::SafeTensors& file = checkpoint.file;
  std::vector<weights::ExpectedTensor> expected;
  for (const ParamEntry& e : ps.entries()) expected.push_back({e.name, e.shape, weights::ValueKind::Float});
  for (const auto& [name, count] : ps.counters()) expected.push_back({name, {}, weights::ValueKind::Integer});
  // The optimiser moments and the INT8 scales (engine/model/calibration.hpp) are not model
  // tensors: check the model's set without them.
  weights::SafeTensors model_part;
  std::map<std::string, Int8Input> int8_inputs;
  const std::string scale_suffix = ".input_scale";
  for (const std::string& name : file.names()) {
    if (name.rfind(kQuantizationPrefix, 0) == 0) {
      if (name.ends_with(scale_suffix)) {
        const std::string key = name.substr(std::string(kQuantizationPrefix).size(),
                                            name.size() - std::string(kQuantizationPrefix).size() - scale_suffix.size());
        Int8Input& input = int8_inputs[key];
        input.scale = file.get_f32(name, {1})[0];
        if (file.contains(input_non_negative_name(key)))
          input.non_negative = file.get_f32(input_non_negative_name(key), {1})[0] != 0.0f;
        if (file.contains(winograd_input_scale_name(key))) {
          const Tensor<float> winograd = file.get_f32(winograd_input_scale_name(key), {16});
          std::copy(winograd.begin(), winograd.end(), input.winograd.begin());
        }
      }
      continue;
    }
    if (name.rfind("optimizer.", 0) != 0) model_part.add(file.at(name));
  }
  weights::check_names_and_shapes(model_part, expected, file.source());
  for (size_t i = 0; i < ps.entries().size(); ++i) {
    const ParamEntry& e = ps.entries()[i];
    ps.upload(static_cast<int>(i), file.get_f32(e.name, e.shape));
  }
  if (!int8_inputs.empty()) net.set_int8_inputs(std::move(int8_inputs));
  for (auto& [name, count] : ps.counters()) {
    const auto v = file.get_i64(name);
    PS_CHECK(v.size() == 1, "{}: {} must hold one integer", file.source(), name);
    count = v[0];
  }
  if (with_optimizer) {
    PS_CHECK(checkpoint.has_optimizer, "{}: no optimizer state (optimizer.exp_avg / exp_avg_sq); cannot resume",
             file.source());
    const Shape flat{ps.num_trainable()};
    const Tensor<float> m = file.get_f32("optimizer.exp_avg", flat), v = file.get_f32("optimizer.exp_avg_sq", flat);
    ps.upload_flat(ps.adam_m(), std::vector<float>(m.begin(), m.end()));
    ps.upload_flat(ps.adam_v(), std::vector<float>(v.begin(), v.end()));
  }
}

RunConfig config_for(const Checkpoint& checkpoint, const fs::path& config_override) {
  if (!config_override.empty()) return load_run_config(config_override);
  if (checkpoint.config) return *checkpoint.config;
  RunConfig config;
  config.model = model_config_from_tensors(checkpoint.file);
  config.source = checkpoint.file.source() + " (architecture from its tensor shapes, the paper's grid)";
  return config;
}

}  // namespace pillarseg
