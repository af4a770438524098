// pillarseg plot RUN_DIR [--out DIR]: a training run's curves from RUN_DIR/metrics.jsonl as PNGs
// in DIR (default RUN_DIR/plots): loss, learning rate and gradient norm per step, and where the
// log has validation lines the validation mIoU and per-class IoU per epoch and the last
// validation's confusion matrix. Everything is read and drawn before the first file is written.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "core/classes.hpp"
#include "core/error.hpp"
#include "engine/cli/commands.hpp"
#include "engine/render/plot.hpp"
#include "engine/util/image.hpp"
#include "engine/util/metrics_log.hpp"

namespace pillarseg::cli {

namespace {

namespace fs = std::filesystem;

struct PlotArgs {
  std::string run_dir, out;
};

const Rgb kBlue{31, 119, 180}, kOrange{255, 127, 14};

Series step_series(const TrainingLog& log, const std::string& name, double StepRecord::*field,
                   Rgb colour, float width) {
  Series s{.name = name, .colour = colour, .line_width = width};
  for (const StepRecord& r : log.steps) {
    s.x.push_back(static_cast<double>(r.step));
    s.y.push_back(r.*field);
  }
  return s;
}

Chart loss_chart(const TrainingLog& log) {
  Chart chart{.title = "Training loss", .x_label = "step", .y_label = "loss", .integer_x = true};
  chart.series.push_back(step_series(log, "loss per step", &StepRecord::loss, kBlue, 1.5f));
  if (!log.epochs.empty()) {
    Series mean{
        .name = "epoch mean loss", .colour = kOrange, .line_width = 2.0f, .marker_radius = 4};
    for (const EpochRecord& e : log.epochs) {
      mean.x.push_back(static_cast<double>(e.step));
      mean.y.push_back(e.mean_loss);
    }
    chart.series.push_back(std::move(mean));
  }
  // A log axis when the loss falls by more than a decade.
  double lo = INFINITY, hi = 0;
  for (const Series& s : chart.series)
    for (const double y : s.y) lo = std::min(lo, y), hi = std::max(hi, y);
  if (lo > 0 && hi > 10 * lo) chart.log_y = true, chart.y_label = "loss (log scale)";
  return chart;
}

Chart lr_chart(const TrainingLog& log) {
  Chart chart{.title = "Learning rate",
              .x_label = "step",
              .y_label = "learning rate",
              .y_from_zero = true,
              .integer_x = true};
  chart.series.push_back(step_series(log, "learning rate", &StepRecord::lr, kBlue, 2.0f));
  return chart;
}

Chart grad_norm_chart(const TrainingLog& log) {
  Chart chart{.title = "Gradient norm (before clipping)",
              .x_label = "step",
              .y_label = "L2 norm of the gradient",
              .y_from_zero = true,
              .integer_x = true};
  chart.series.push_back(step_series(log, "gradient norm", &StepRecord::grad_norm, kBlue, 1.5f));
  return chart;
}

std::string eval_kind(const TrainingLog& log) {
  return log.evals.back().mode + " eval";
}

Chart miou_chart(const TrainingLog& log) {
  const EvalRecord* best = nullptr;
  Series s{.name = "mIoU", .colour = kBlue, .line_width = 2.0f, .marker_radius = 4};
  for (const EvalRecord& e : log.evals) {
    s.x.push_back(static_cast<double>(e.epoch));
    s.y.push_back(100 * e.miou);
    if (std::isfinite(e.miou) && (best == nullptr || e.miou > best->miou)) best = &e;
  }
  Chart chart{.title = fmt::format("Validation mIoU ({}): best {:.1f}% at epoch {}", eval_kind(log),
                                   100 * best->miou, best->epoch),
              .x_label = "epoch",
              .y_label = "mIoU [%]",
              .y_from_zero = true,
              .integer_x = true};
  chart.series.push_back(std::move(s));
  return chart;
}

Chart per_class_chart(const TrainingLog& log, const ClassTable& classes) {
  Chart chart{.title = fmt::format("Validation IoU per class ({})", eval_kind(log)),
              .x_label = "epoch",
              .y_label = "IoU [%]",
              .y_range = std::pair{0.0, 100.0},
              .integer_x = true};
  for (int c = 0; c < kNumClasses; ++c) {
    Series s{.name = log.evals.back().class_names[c],
             .colour = classes.color(c + 1),
             .line_width = 2.0f,
             .marker_radius = 3};
    for (const EvalRecord& e : log.evals) {
      s.x.push_back(static_cast<double>(e.epoch));
      s.y.push_back(100 * e.iou[c]);
    }
    chart.series.push_back(std::move(s));
  }
  return chart;
}

// 1234 -> "1234", 12345 -> "12.3k", 1234567 -> "1.23M".
std::string short_count(int64_t n) {
  if (n < 10000) return fmt::format("{}", n);
  if (n < 1000000) return fmt::format("{:.1f}k", static_cast<double>(n) / 1e3);
  return fmt::format("{:.2f}M", static_cast<double>(n) / 1e6);
}

std::string percent(double share) {
  const double p = 100 * share;
  if (p >= 9.95) return fmt::format("{:.0f}%", p);
  if (p >= 0.05) return fmt::format("{:.1f}%", p);
  return "<0.1%";
}

// Rows normalised to their true-class totals; each cell its share and its count.
HeatMap confusion_map(const EvalRecord& e) {
  HeatMap map;
  map.title = fmt::format("Confusion matrix, epoch {} ({} eval): each row as % of its true class",
                          e.epoch, e.mode);
  map.x_label = "predicted class";
  map.y_label = "true class (labelled cells)";
  for (int r = 0; r < kNumClasses; ++r) {
    int64_t total = 0;
    for (const int64_t v : e.confusion[r]) total += v;
    map.row_names.push_back(fmt::format("{} ({})", e.class_names[r], short_count(total)));
    map.column_names.push_back(e.class_names[r]);
    std::vector<double>& shade = map.shade.emplace_back();
    std::vector<std::string>& text = map.text.emplace_back();
    for (int c = 0; c < kNumClasses; ++c) {
      const int64_t v = e.confusion[r][c];
      const double share = total > 0 ? static_cast<double>(v) / static_cast<double>(total) : NAN;
      shade.push_back(share);
      text.push_back(total == 0 ? "" : v == 0 ? "0" : percent(share) + "\n" + short_count(v));
    }
  }
  return map;
}

void run_plot(const PlotArgs& args) {
  const fs::path run_dir(args.run_dir);
  const fs::path out = args.out.empty() ? run_dir / "plots" : fs::path(args.out);
  const fs::path log_path = run_dir / "metrics.jsonl";
  const TrainingLog log = read_training_log(log_path);
  PS_CHECK(!log.steps.empty(), "{}: no step lines, nothing to plot (has the run trained a step?)",
           log_path.string());
  const Font font(find_font());
  const ClassTable classes = ClassTable::defaults();

  std::vector<std::pair<std::string, ImageRgb>> images;
  std::vector<std::string> skipped;
  images.emplace_back("loss.png", render_chart(loss_chart(log), font));
  images.emplace_back("lr.png", render_chart(lr_chart(log), font));
  images.emplace_back("grad_norm.png", render_chart(grad_norm_chart(log), font));
  if (log.evals.empty()) {
    skipped.push_back(
        fmt::format("val_miou.png, val_iou_per_class.png, confusion.png (no eval lines in {}: "
                    "validation runs with eval.every_epochs)",
                    log_path.string()));
  } else {
    const auto any_eval = [&](auto predicate) {
      return std::any_of(log.evals.begin(), log.evals.end(), predicate);
    };
    if (any_eval([](const EvalRecord& e) { return std::isfinite(e.miou); }))
      images.emplace_back("val_miou.png", render_chart(miou_chart(log), font));
    else
      skipped.push_back("val_miou.png (every eval line's mIoU is null)");
    if (any_eval([](const EvalRecord& e) {
          return std::any_of(e.iou.begin(), e.iou.end(), [](double v) { return std::isfinite(v); });
        }))
      images.emplace_back("val_iou_per_class.png",
                          render_chart(per_class_chart(log, classes), font));
    else
      skipped.push_back("val_iou_per_class.png (every class's IoU is null in every eval line)");
    if (!log.evals.back().confusion.empty())
      images.emplace_back("confusion.png", render_heat_map(confusion_map(log.evals.back()), font));
    else
      skipped.push_back(
          "confusion.png (the last eval line has no confusion matrix: a log from an older "
          "pillarseg)");
  }

  fs::create_directories(out);
  std::string written;
  for (const auto& [name, image] : images) {
    write_png_rgb(out / name, image);
    written += (written.empty() ? "" : ", ") + name;
  }
  std::string skipped_text;
  for (const std::string& s : skipped)
    skipped_text += (skipped_text.empty() ? "; skipped " : "; ") + s;
  fmt::print("plot: wrote {} in {}{}\n", written, out.string(), skipped_text);
}

}  // namespace

void add_plot(CLI::App& app) {
  auto args = std::make_shared<PlotArgs>();
  CLI::App* cmd = app.add_subcommand("plot",
                                     "Training curves of a run (RUN_DIR/metrics.jsonl) as PNGs: "
                                     "loss, learning rate, gradient norm, "
                                     "validation mIoU and per-class IoU, confusion matrix");
  cmd->add_option("run_dir", args->run_dir,
                  "the run directory (train --out), holding metrics.jsonl")
      ->required();
  cmd->add_option("--out", args->out, "the directory of the PNGs (default: RUN_DIR/plots)");
  cmd->callback([args] { run_plot(*args); });
}

}  // namespace pillarseg::cli
