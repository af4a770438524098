#include "engine/util/metrics_log.hpp"

#include <cmath>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <string_view>

#include "core/error.hpp"

namespace pillarseg {

namespace {

// ordered_json keeps the "iou" object's classes in the order the trainer wrote them (id order).
using Json = nlohmann::ordered_json;

// One line of the log being read: its fields, with errors naming file:line.
class Line {
 public:
  Line(const Json& object, std::string where) : object_(object), where_(std::move(where)) {}

  const Json& field(const char* key) const {
    const auto it = object_.find(key);
    PS_CHECK(it != object_.end(), "{}: {} line has no \"{}\"", where_, type(), key);
    return *it;
  }
  double number(const char* key) const {
    const Json& v = field(key);
    PS_CHECK(v.is_number(), "{}: \"{}\" must be a number, got {}", where_, key, v.dump());
    return v.get<double>();
  }
  // A number, or NaN for null.
  double number_or_null(const char* key) const {
    const Json& v = field(key);
    if (v.is_null()) return std::numeric_limits<double>::quiet_NaN();
    return number(key);
  }
  // A number, or NaN where the line has no such field (logs from before the trainer wrote it).
  double number_if_present(const char* key) const {
    return object_.contains(key) ? number(key) : std::numeric_limits<double>::quiet_NaN();
  }
  int64_t count(const char* key) const {
    const Json& v = field(key);
    PS_CHECK(v.is_number_integer() && v.get<int64_t>() >= 0,
             "{}: \"{}\" must be an integer >= 0, got {}", where_, key, v.dump());
    return v.get<int64_t>();
  }
  std::string text(const char* key) const {
    const Json& v = field(key);
    PS_CHECK(v.is_string(), "{}: \"{}\" must be a string, got {}", where_, key, v.dump());
    return v.get<std::string>();
  }
  std::string type() const { return object_.at("type").get<std::string>(); }
  const std::string& where() const { return where_; }

 private:
  const Json& object_;
  std::string where_;
};

StepRecord read_step(const Line& line) {
  StepRecord r;
  r.epoch = line.count("epoch");
  r.step = line.count("step");
  r.loss = line.number("loss");
  r.lr = line.number("lr");
  r.beta1 = line.number("beta1");
  r.grad_norm = line.number("grad_norm");
  r.elapsed_s = line.number("elapsed_s");
  return r;
}

EpochRecord read_epoch(const Line& line) {
  EpochRecord r;
  r.epoch = line.count("epoch");
  r.step = line.count("step");
  r.mean_loss = line.number("mean_loss");
  r.data_wait_s = line.number_if_present("data_wait_s");
  r.checkpoint = line.text("checkpoint");
  return r;
}

EvalRecord read_eval(const Line& line, const Json& object) {
  EvalRecord r;
  r.epoch = line.count("epoch");
  r.step = line.count("step");
  r.mode = line.text("mode");
  r.miou = line.number_or_null("miou");
  r.labelled_cells = line.count("labelled_cells");
  r.best_epoch = line.count("best_epoch");
  const Json& iou = line.field("iou");
  PS_CHECK(iou.is_object() && iou.size() == kNumClasses,
           "{}: \"iou\" must be an object of {} classes, got {}", line.where(), kNumClasses,
           iou.dump());
  int c = 0;
  for (const auto& [name, value] : iou.items()) {
    PS_CHECK(value.is_number() || value.is_null(),
             "{}: \"iou\": \"{}\" must be a number or null, got {}", line.where(), name,
             value.dump());
    r.class_names[c] = name;
    r.iou[c] = value.is_null() ? std::numeric_limits<double>::quiet_NaN() : value.get<double>();
    ++c;
  }
  if (!object.contains("confusion")) return r;
  const Json& confusion = object["confusion"];
  const auto bad_matrix = [&] {
    PS_FAIL("{}: \"confusion\" must be {} rows of {} integers >= 0, got {}", line.where(),
            kNumClasses, kNumClasses, confusion.dump());
  };
  if (!confusion.is_array() || confusion.size() != kNumClasses) bad_matrix();
  for (const Json& row : confusion) {
    if (!row.is_array() || row.size() != kNumClasses) bad_matrix();
    std::array<int64_t, kNumClasses>& out = r.confusion.emplace_back();
    for (int k = 0; k < kNumClasses; ++k) {
      const Json& v = row[static_cast<size_t>(k)];
      if (!v.is_number_integer() || v.get<int64_t>() < 0) bad_matrix();
      out[k] = v.get<int64_t>();
    }
  }
  return r;
}

// nlohmann's messages start with "[json.exception.parse_error.101] parse error at line 1, ...";
// the line is ours to name, the column and the reason are kept.
std::string parse_reason(std::string_view what) {
  const size_t at = what.find("column");
  return std::string(at == std::string_view::npos ? what : what.substr(at));
}

}  // namespace

TrainingLog read_training_log(const std::filesystem::path& path) {
  PS_CHECK(std::filesystem::is_regular_file(path),
           "{}: no such file (a training run directory holds metrics.jsonl)", path.string());
  std::ifstream in(path);
  PS_CHECK(in, "{}: cannot open for reading", path.string());
  TrainingLog log;
  std::string text;
  for (int64_t number = 1; std::getline(in, text); ++number) {
    if (text.find_first_not_of(" \t\r") == std::string::npos) continue;
    const std::string where = fmt::format("{}:{}", path.string(), number);
    Json object;
    try {
      object = Json::parse(text);
    } catch (const Json::parse_error& e) {
      PS_FAIL("{}: not valid JSON: {}", where, parse_reason(e.what()));
    } catch (const Json::exception& e) {  // a number beyond double's range, ...
      PS_FAIL("{}: not a log line: {}", where, e.what());
    }
    PS_CHECK(object.is_object(), "{}: not a JSON object: {}", where, text);
    const auto type = object.find("type");
    PS_CHECK(type != object.end() && type->is_string(),
             "{}: no \"type\" string (step, epoch or eval)", where);
    const Line line(object, where);
    if (*type == "step") {
      log.steps.push_back(read_step(line));
    } else if (*type == "epoch") {
      log.epochs.push_back(read_epoch(line));
    } else if (*type == "eval") {
      log.evals.push_back(read_eval(line, object));
    }
  }
  PS_CHECK(!in.bad(), "{}: read error", path.string());
  return log;
}

}  // namespace pillarseg
