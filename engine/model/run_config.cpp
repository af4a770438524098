#include "engine/model/run_config.hpp"

#include <yaml-cpp/yaml.h>

#include <numbers>

#include "core/error.hpp"
#include "core/io.hpp"
#include "engine/model/memory_estimate.hpp"

namespace pillarseg {

namespace {

template <class T>
T get(const YAML::Node& node, const std::string& where) {
  try {
    return node.as<T>();
  } catch (const YAML::Exception& e) {
    PS_FAIL("{}: {}", where, e.what());
  }
}

void read_train(const YAML::Node& t, const ClassTable& classes, const std::string& source, TrainConfig& c) {
  YAML::Node coefficients;
  for (const auto& kv : t) {
    const std::string key = kv.first.as<std::string>();
    const YAML::Node& v = kv.second;
    const std::string where = source + ": train." + key;
    if (key == "ground_truth") c.ground_truth = parse_ground_truth_kind(get<std::string>(v, where));
    else if (key == "loss") {
      const std::string l = get<std::string>(v, where);
      PS_CHECK(l == "ce" || l == "bce" || l == "ce+lovasz", "{}: expected ce, bce or ce+lovasz, got '{}'",
               where, l);
      c.loss = l == "ce" ? LossKind::CrossEntropy : l == "bce" ? LossKind::Bce : LossKind::CrossEntropyLovasz;
    } else if (key == "epochs") c.epochs = get<int>(v, where);
    else if (key == "batch_size") c.batch_size = get<int>(v, where);
    else if (key == "seed") c.seed = get<uint64_t>(v, where);
    else if (key == "max_scans_per_sequence") c.max_scans_per_sequence = get<int>(v, where);
    else if (key == "scan_stride") c.scan_stride = get<int>(v, where);
    else if (key == "precise_bn_batches") c.precise_bn_batches = get<int>(v, where);
    else if (key == "average_epochs") c.average_epochs = get<int>(v, where);
    else if (key == "workers") {
      c.workers = get<int>(v, where);
      PS_CHECK(c.workers >= 0 && c.workers <= 64, "{}: expected 0..64 threads, got {}", where, c.workers);
    }
    else if (key == "gradient_bucket_mb") {
      c.gradient_bucket_mb = get<double>(v, where);
      PS_CHECK(c.gradient_bucket_mb >= 0 && c.gradient_bucket_mb <= 4096, "{}: expected 0..4096 MiB, got {}", where,
               c.gradient_bucket_mb);
    }
    else if (key == "sequences") c.sequences = get<std::vector<int>>(v, where);
    else if (key == "coefficients") coefficients = v;
    else if (key == "optimizer") {
      for (const auto& o : v) {
        const std::string k = o.first.as<std::string>();
        const std::string w = where + "." + k;
        if (k == "lr") c.lr = get<double>(o.second, w);
        else if (k == "weight_decay") c.weight_decay = get<double>(o.second, w);
        else if (k == "beta2") c.beta2 = get<double>(o.second, w);
        else if (k == "eps") c.eps = get<double>(o.second, w);
        else if (k == "schedule") {
          const std::string s = get<std::string>(o.second, w);
          PS_CHECK(s == "onecycle" || s == "constant", "{}: expected onecycle or constant, got '{}'", w, s);
          c.onecycle = s == "onecycle";
        } else if (k == "div_factor") c.div_factor = get<double>(o.second, w);
        else if (k == "pct_start") c.pct_start = get<double>(o.second, w);
        else if (k == "moms") {
          const auto m = get<std::vector<double>>(o.second, w);
          PS_CHECK(m.size() == 2, "{}: expected [max, min], got {} values", w, m.size());
          c.momentum_max = m[0], c.momentum_min = m[1];
        } else if (k == "grad_clip") c.grad_clip = get<double>(o.second, w);
        else PS_FAIL("{}: unknown key", w);
      }
    } else if (key == "augmentation") {
      if (v.IsScalar()) {
        c.augment = get<bool>(v, where);
        continue;
      }
      for (const auto& a : v) {
        const std::string k = a.first.as<std::string>();
        const std::string w = where + "." + k;
        if (k == "flip_x") c.augmentation.flip_x = get<bool>(a.second, w);
        else if (k == "flip_y") c.augmentation.flip_y = get<bool>(a.second, w);
        else if (k == "rotate") c.augmentation.rotate = get<bool>(a.second, w);
        else if (k == "scale") c.augmentation.scale = get<bool>(a.second, w);
        else if (k == "translate") c.augmentation.translate = get<bool>(a.second, w);
        else if (k == "tilt_deg") c.augmentation.tilt = get<double>(a.second, w) * std::numbers::pi / 180.0;
        else if (k == "height") c.augmentation.height = get<double>(a.second, w);
        else if (k == "reflectance_jitter") c.augmentation.reflectance_jitter = get<bool>(a.second, w);
        else if (k == "reflectance_dropout") c.augmentation.reflectance_dropout = get<double>(a.second, w);
        else if (k == "point_dropout") c.augmentation.point_dropout = get<double>(a.second, w);
        else if (k == "grade_change") c.augmentation.grade_change = get<double>(a.second, w);
        else PS_FAIL("{}: unknown key", w);
      }
    } else {
      PS_FAIL("{}: unknown key", where);
    }
  }
  c.coefficients = default_coefficients(c.ground_truth);
  if (coefficients) {
    for (const auto& kv : coefficients) {
      const std::string name = kv.first.as<std::string>();
      int id = -1;
      for (int k = 1; k < kNumClassIds; ++k)
        if (classes.name(k) == name) id = k;
      PS_CHECK(id > 0, "{}: train.coefficients: unknown class '{}'", source, name);
      c.coefficients[static_cast<size_t>(id)] = get<float>(kv.second, source + ": train.coefficients." + name);
    }
  }
  PS_CHECK(c.epochs >= 1, "{}: train.epochs must be >= 1, got {}", source, c.epochs);
  PS_CHECK(c.batch_size >= 1, "{}: train.batch_size must be >= 1, got {}", source, c.batch_size);
  PS_CHECK(c.scan_stride >= 1, "{}: train.scan_stride must be >= 1, got {}", source, c.scan_stride);
  PS_CHECK(c.precise_bn_batches >= 0, "{}: train.precise_bn_batches must be >= 0, got {}", source,
           c.precise_bn_batches);
  PS_CHECK(c.average_epochs >= 0 && c.average_epochs <= c.epochs,
           "{}: train.average_epochs must be 0..train.epochs ({}), got {}", source, c.epochs,
           c.average_epochs);
  PS_CHECK(c.average_epochs == 0 || c.precise_bn_batches > 0,
           "{}: train.average_epochs {} needs train.precise_bn_batches > 0 (the averaged weights' "
           "BatchNorm statistics are estimated again)",
           source, c.average_epochs);
  PS_CHECK(c.lr > 0, "{}: train.optimizer.lr must be > 0, got {}", source, c.lr);
  PS_CHECK(c.pct_start > 0 && c.pct_start < 1, "{}: train.optimizer.pct_start must be in (0, 1)", source);
  try {
    validate_augmentation(c.augmentation);
  } catch (const Error& e) {
    PS_FAIL("{}: train.{}", source, e.what());
  }
}

}  // namespace

std::array<float, kNumClassIds> default_coefficients(GroundTruthKind kind) {
  std::array<float, kNumClassIds> c;
  c.fill(1.0f);
  c[0] = 0.0f;
  c[1] = kind == GroundTruthKind::dense ? 5.0f : 2.0f;
  c[2] = c[3] = c[4] = 8.0f;
  return c;
}

namespace {
RunConfig run_config_from_yaml(const YAML::Node& root, const std::string& yaml_text, const std::string& source);
}  // namespace

RunConfig parse_run_config(const std::string& yaml_text, const std::string& source) {
  YAML::Node root;
  try {
    root = YAML::Load(yaml_text);
  } catch (const YAML::Exception& e) {
    PS_FAIL("{}: not valid YAML: {}", source, e.what());
  }
  PS_CHECK(root.IsMap() || root.IsNull(), "{}: expected a mapping with grid/model/train/eval sections", source);
  // What the readers below do not check themselves (a key that is not a scalar, a section that is
  // a sequence) yaml-cpp reports with an exception: it becomes this file's error.
  try {
    return run_config_from_yaml(root, yaml_text, source);
  } catch (const YAML::Exception& e) {
    PS_FAIL("{}: {}", source, e.what());
  }
}

namespace {

RunConfig run_config_from_yaml(const YAML::Node& root, const std::string& yaml_text, const std::string& source) {
  for (const auto& kv : root) {
    const std::string key = kv.first.as<std::string>();
    PS_CHECK(key == "grid" || key == "model" || key == "train" || key == "eval" || key == "input",
             "{}: unknown section '{}' (expected grid, model, train, eval, input)", source, key);
  }
  RunConfig c;
  c.text = yaml_text;
  c.source = source;
  c.model = model_config_from_yaml(root, source);
  read_train(root["train"] ? root["train"] : YAML::Node(YAML::NodeType::Map), ClassTable::defaults(), source,
             c.train);
  try {
    check_index_limits(c.model, c.train.batch_size);
  } catch (const Error& e) {
    PS_FAIL("{}: train.batch_size {}: {}", source, c.train.batch_size, e.what());
  }
  if (const YAML::Node e = root["eval"]) {
    for (const auto& kv : e) {
      const std::string key = kv.first.as<std::string>();
      if (key == "sequences") c.eval.sequences = get<std::vector<int>>(kv.second, source + ": eval.sequences");
      else if (key == "scan_stride") c.eval.scan_stride = get<int>(kv.second, source + ": eval.scan_stride");
      else if (key == "every_epochs") {
        c.eval.every_epochs = get<int>(kv.second, source + ": eval.every_epochs");
        PS_CHECK(c.eval.every_epochs >= 0, "{}: eval.every_epochs must be >= 0 (0: off), got {}", source,
                 c.eval.every_epochs);
      } else if (key == "mode") c.eval.mode = parse_ground_truth_kind(get<std::string>(kv.second, source + ": eval.mode"));
      else if (key == "flips") {
        c.eval.flips = get<int>(kv.second, source + ": eval.flips");
        check_flips(c.eval.flips, c.model.grid, source + ": eval.flips");
      } else PS_FAIL("{}: eval.{}: unknown key", source, key);
    }
    PS_CHECK(c.eval.scan_stride >= 1, "{}: eval.scan_stride must be >= 1", source);
  }
  if (const YAML::Node input = root["input"]) c.input = parse_input_mapping(input, source + ": input");
  return c;
}

}  // namespace

RunConfig load_run_config(const std::filesystem::path& path) {
  PS_CHECK(std::filesystem::exists(path), "--config {}: no such file", path.string());
  return parse_run_config(read_file_text(path), path.string());
}

}  // namespace pillarseg
