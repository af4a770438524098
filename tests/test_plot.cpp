// `pillarseg plot`'s parts: the tick chooser and tick labels on hand-computed cases, the reader
// of metrics.jsonl (null values, skipped line types, malformed lines named by file:line), the
// font lookup, and rendered charts and heat maps checked pixel by pixel.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <string>

#include "core/error.hpp"
#include "engine/render/plot.hpp"
#include "engine/util/metrics_log.hpp"
#include "tests/support/image_checks.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using pillarseg::test::count_dark;
using pillarseg::test::is_white;
namespace fs = std::filesystem;

using pillarseg::test::error_of;

namespace {

void expect_ticks(const Ticks& got, double step, const std::vector<double>& values) {
  EXPECT_NEAR(got.step, step, 1e-12 * step);
  ASSERT_EQ(got.values.size(), values.size()) << "step " << got.step;
  for (size_t i = 0; i < values.size(); ++i)
    EXPECT_NEAR(got.values[i], values[i], 1e-12) << "tick " << i;
}

void write_text(const fs::path& path, const std::string& text) {
  std::ofstream(path) << text;
}

int64_t count_colour(const ImageRgb& image, Rgb c, int x0 = 0, int y0 = 0, int x1 = -1,
                     int y1 = -1) {
  if (x1 < 0) x1 = image.width;
  if (y1 < 0) y1 = image.height;
  int64_t n = 0;
  for (int y = y0; y < y1; ++y)
    for (int x = x0; x < x1; ++x) {
      const uint8_t* p = image.at(x, y);
      n += p[0] == c.r && p[1] == c.g && p[2] == c.b;
    }
  return n;
}



const std::string kIou =
    R"({"vehicle": 0.5, "person": null, "two-wheel": 0.1, "rider": 0.0, "road": 0.9, "sidewalk": 0.6, )"
    R"("other-ground": 0.4, "building": 0.7, "object": 0.05, "vegetation": 0.8, "trunk": 0.01, "terrain": 0.75})";

std::string confusion_json(int rows) {
  std::string out = "[";
  for (int r = 0; r < rows; ++r) {
    out += r ? ", [" : "[";
    for (int c = 0; c < kNumClasses; ++c)
      out += (c ? ", " : "") + std::to_string(r == c ? 10 * (r + 1) : c);
    out += "]";
  }
  return out + "]";
}

std::string eval_line(const std::string& miou, const std::string& confusion) {
  return R"({"type": "eval", "epoch": 2, "step": 4, "mode": "sparse", "miou": )" + miou +
         R"(, "labelled_cells": 1234, "best_epoch": 2, "iou": )" + kIou +
         (confusion.empty() ? "" : R"(, "confusion": )" + confusion) + "}";
}

const std::string kStep1 =
    R"({"type": "step", "epoch": 1, "step": 1, "loss": 2.5, "lr": 3.000000e-04, "beta1": 0.9500, "grad_norm": 1.5, "elapsed_s": 0.10})";
const std::string kStep2 =
    R"({"type": "step", "epoch": 1, "step": 2, "loss": 2.25, "lr": 6.000000e-04, "beta1": 0.9400, "grad_norm": 1.25, "elapsed_s": 0.20})";
const std::string kEpoch =
    R"({"type": "epoch", "epoch": 1, "step": 2, "mean_loss": 2.375, "data_wait_s": 0.012, "checkpoint": "checkpoint.safetensors"})";

}  // namespace

TEST(PlotTicks, NiceStepsOnHandComputedRanges) {
  // 0.73 / 0.05 gives 15 ticks, more than 10; 0.1 gives 0, 0.1, .., 0.7.
  expect_ticks(nice_ticks(0, 0.73), 0.1, {0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7});
  // 0.1 would give 11 ticks.
  expect_ticks(nice_ticks(0, 1), 0.2, {0, 0.2, 0.4, 0.6, 0.8, 1.0});
  // Steps 1..60: 5 gives 12 ticks, 10 gives 6.
  expect_ticks(nice_ticks(1, 60), 10, {10, 20, 30, 40, 50, 60});
  // A negative start: 2 gives 25 ticks (-2..46), 5 gives 0..45.
  expect_ticks(nice_ticks(-3.2, 47), 5, {0, 5, 10, 15, 20, 25, 30, 35, 40, 45});
  // Around zero: 0.2 would give 11 ticks.
  expect_ticks(nice_ticks(-1, 1), 0.5, {-1, -0.5, 0, 0.5, 1});
  // Learning rates: 0.0002 gives 14 ticks (0.0004..0.003), 0.0005 gives 6.
  expect_ticks(nice_ticks(0.0003, 0.003), 0.0005, {0.0005, 0.001, 0.0015, 0.002, 0.0025, 0.003});
  // Fewer ticks asked: 0..0.73 in at most 4 -> 0.2.
  expect_ticks(nice_ticks(0, 0.73, 4), 0.2, {0, 0.2, 0.4, 0.6});
  EXPECT_NE(error_of([] { nice_ticks(1, 1); }).find("lo < hi"), std::string::npos);
  EXPECT_NE(error_of([] { nice_ticks(0, NAN); }).find("finite"), std::string::npos);
}

TEST(PlotTicks, LogTicksAndLabels) {
  // 1-2-5 inside [0.3, 4]: 0.5, 1, 2.
  expect_ticks(log_ticks(0.3, 4), 0, {0.5, 1, 2});
  // [0.01, 100] has 13 1-2-5 values: the decades alone.
  expect_ticks(log_ticks(0.01, 100), 0, {0.01, 0.1, 1, 10, 100});
  // 1e-6 .. 1e6 (13 decades) in at most 5: every third decade.
  expect_ticks(log_ticks(1e-6, 1e6, 5), 0, {1e-6, 1e-3, 1, 1e3, 1e6});
  EXPECT_NE(error_of([] { log_ticks(0, 1); }).find("0 < lo"), std::string::npos);

  EXPECT_EQ(tick_label(0.1 + 0.2, 0.1), "0.3");
  EXPECT_EQ(tick_label(20, 10), "20");
  EXPECT_EQ(tick_label(-0.2, 0.1), "-0.2");
  EXPECT_EQ(tick_label(0.25, 0.05), "0.25");
  EXPECT_EQ(tick_label(0.001, 0.0005), "0.0010");
  EXPECT_EQ(tick_label(1e-17, 0.1), "0");
  EXPECT_EQ(tick_label(2.5e-5, 5e-6), "2.5e-5");
  EXPECT_EQ(tick_label(1e-5, 1e-5), "1e-5");
  EXPECT_EQ(tick_label(2e6, 1e6), "2e+6");
}

TEST(MetricsLog, ReadsStepsEpochsAndEvalsWithNulls) {
  const fs::path path = test::temp_dir() / "metrics.jsonl";
  write_text(
      path, kStep1 + "\n" + kStep2 + "\n" + eval_line("null", confusion_json(kNumClasses)) + "\n" +
                kEpoch + "\n" + R"({"type": "a later kind", "x": 1})" + "\n\n" +
                eval_line("0.25", "") + "\n" +
                R"({"type": "epoch", "epoch": 2, "step": 4, "mean_loss": 2.0, "checkpoint": "c"})" +
                "\n");
  const TrainingLog log = read_training_log(path);
  ASSERT_EQ(log.steps.size(), 2u);
  EXPECT_EQ(log.steps[1].epoch, 1);
  EXPECT_EQ(log.steps[1].step, 2);
  EXPECT_DOUBLE_EQ(log.steps[1].loss, 2.25);
  EXPECT_DOUBLE_EQ(log.steps[0].lr, 3e-4);
  EXPECT_DOUBLE_EQ(log.steps[1].beta1, 0.94);
  EXPECT_DOUBLE_EQ(log.steps[1].grad_norm, 1.25);
  EXPECT_DOUBLE_EQ(log.steps[1].elapsed_s, 0.2);
  ASSERT_EQ(log.epochs.size(), 2u);
  EXPECT_DOUBLE_EQ(log.epochs[0].mean_loss, 2.375);
  EXPECT_DOUBLE_EQ(log.epochs[0].data_wait_s, 0.012);
  EXPECT_EQ(log.epochs[0].checkpoint, "checkpoint.safetensors");
  EXPECT_TRUE(std::isnan(log.epochs[1].data_wait_s));  // a log from before the trainer wrote it
  ASSERT_EQ(log.evals.size(), 2u);
  const EvalRecord& e = log.evals[0];
  EXPECT_EQ(e.epoch, 2);
  EXPECT_EQ(e.step, 4);
  EXPECT_EQ(e.mode, "sparse");
  EXPECT_TRUE(std::isnan(e.miou));
  EXPECT_EQ(e.labelled_cells, 1234);
  EXPECT_EQ(e.best_epoch, 2);
  // The classes in the log's order (ClassTable id order), not sorted by name.
  const ClassTable classes = ClassTable::defaults();
  for (int c = 0; c < kNumClasses; ++c) EXPECT_EQ(e.class_names[c], classes.name(c + 1));
  EXPECT_DOUBLE_EQ(e.iou[0], 0.5);
  EXPECT_TRUE(std::isnan(e.iou[1]));
  EXPECT_DOUBLE_EQ(e.iou[11], 0.75);
  ASSERT_EQ(e.confusion.size(), static_cast<size_t>(kNumClasses));
  EXPECT_EQ(e.confusion[0][0], 10);
  EXPECT_EQ(e.confusion[11][11], 120);
  EXPECT_EQ(e.confusion[3][5], 5);
  EXPECT_DOUBLE_EQ(log.evals[1].miou, 0.25);
  EXPECT_TRUE(log.evals[1].confusion.empty());  // a log from before the trainer wrote it
}

TEST(MetricsLog, BadInputNamesFileAndLine) {
  const fs::path dir = test::temp_dir();
  const fs::path missing = dir / "none" / "metrics.jsonl";
  EXPECT_NE(error_of([&] { read_training_log(missing); }).find(missing.string() + ": no such file"),
            std::string::npos);

  const fs::path path = dir / "metrics.jsonl";
  const auto error_for = [&](const std::string& third_line) {
    write_text(path, kStep1 + "\n" + kStep2 + "\n" + third_line + "\n" + kEpoch + "\n");
    return error_of([&] { read_training_log(path); });
  };
  const std::string where = path.string() + ":3: ";
  std::string e = error_for(R"({"type": "step", "epoch": 1,)");  // cut short
  EXPECT_NE(e.find(where + "not valid JSON: column"), std::string::npos) << e;
  e = error_for(R"({"type": "step", "epoch": 1, "step": 3, "lr": 0.1})");
  EXPECT_NE(e.find(where + "step line has no \"loss\""), std::string::npos) << e;
  e = error_for(R"({"type": "step", "epoch": 1, "step": 3, "loss": "2.0", "lr": 0.1})");
  EXPECT_NE(e.find(where + "\"loss\" must be a number, got \"2.0\""), std::string::npos) << e;
  e = error_for(R"({"type": "epoch", "epoch": -1, "step": 3})");
  EXPECT_NE(e.find(where + "\"epoch\" must be an integer >= 0, got -1"), std::string::npos) << e;
  e = error_for(R"([1, 2])");
  EXPECT_NE(e.find(where + "not a JSON object"), std::string::npos) << e;
  e = error_for(R"({"epoch": 1})");
  EXPECT_NE(e.find(where + "no \"type\""), std::string::npos) << e;
  e = error_for(eval_line("0.5", confusion_json(kNumClasses - 1)));
  EXPECT_NE(e.find(where + "\"confusion\" must be 12 rows of 12 integers >= 0"), std::string::npos)
      << e;
  e = error_for(
      R"({"type": "eval", "epoch": 2, "step": 4, "mode": "sparse", "miou": null, "labelled_cells": 0, )"
      R"("best_epoch": 0, "iou": {"vehicle": 0.5}})");
  EXPECT_NE(e.find(where + "\"iou\" must be an object of 12 classes"), std::string::npos) << e;
  e = error_for(eval_line("true", ""));
  EXPECT_NE(e.find(where + "\"miou\" must be a number, got true"), std::string::npos) << e;
  // The line before is good: it is line 3 that is named.
  EXPECT_EQ(error_for(kStep2), "");
}

TEST(PlotFont, FoundAtRunTimeWithAnOverride) {
  const char* saved = std::getenv("PILLARSEG_FONT");
  const std::string saved_value = saved ? saved : "";
  const fs::path missing = test::temp_dir() / "NoSuchFont.ttf";
  setenv("PILLARSEG_FONT", missing.c_str(), 1);
  const std::string e = error_of([] { find_font(); });
  EXPECT_NE(e.find("PILLARSEG_FONT=" + missing.string() + ": no such font file"), std::string::npos)
      << e;
  // Not a font: FreeType refuses it, and the message names the file.
  const fs::path not_font = test::temp_dir() / "not_a_font.ttf";
  write_text(not_font, "not a font");
  const std::string e2 = error_of([&] { Font f(not_font); });
  EXPECT_NE(e2.find(not_font.string() + ": FreeType cannot open this font"), std::string::npos)
      << e2;
  unsetenv("PILLARSEG_FONT");
  // The default font missing: the message names the file and the Debian package.
  const fs::path no_default = test::temp_dir() / "dejavu" / "DejaVuSans.ttf";
  const std::string e3 = error_of([&] { find_font(no_default); });
  EXPECT_NE(e3.find(no_default.string() +
                    ": no such font file; install the Debian package fonts-dejavu-core"),
            std::string::npos)
      << e3;
  const fs::path found = find_font();
  EXPECT_EQ(found.filename(), "DejaVuSans.ttf");
  if (saved) setenv("PILLARSEG_FONT", saved_value.c_str(), 1);

  const Font font(found);
  EXPECT_GT(font.text_width("MMMM", 12), font.text_width("iiii", 12));
  EXPECT_GT(font.text_width("MMMM", 24), font.text_width("MMMM", 12));
  EXPECT_EQ(font.text_width("", 12), 0);
  EXPECT_GT(font.ascender(12), 8);
}

TEST(PlotChart, RendersSeriesAxesTextAndLegend) {
  const Font font(find_font());
  const Rgb red{200, 30, 40}, green{20, 160, 60};
  Chart chart{
      .title = "A known series", .x_label = "step", .y_label = "loss", .width = 640, .height = 400};
  Series s{.name = "x squared", .colour = red, .line_width = 2.0f};
  for (int i = 0; i <= 100; ++i) s.x.push_back(i / 10.0), s.y.push_back(i * i / 100.0);
  chart.series.push_back(s);
  const ImageRgb one = render_chart(chart, font);
  EXPECT_EQ(one.width, 640);
  EXPECT_EQ(one.height, 400);
  for (const auto& [x, y] : {std::pair{0, 0}, {639, 0}, {0, 399}, {639, 399}})
    EXPECT_TRUE(is_white(one, x, y)) << "corner " << x << ", " << y;
  // The curve from (0, 0) to (10, 100): well over 300 pixels of its exact colour (the inside of
  // a 2-pixel line about 330 pixels long), none in the left or bottom margins.
  EXPECT_GT(count_colour(one, red), 300);
  EXPECT_EQ(count_colour(one, red, 0, 0, 40, 400), 0);
  EXPECT_EQ(count_colour(one, red, 0, 360, 640, 400), 0);
  // The title: dark text pixels in the top band's middle; none there without a title.
  const int64_t title_ink = count_dark(one, 200, 0, 440, 32);
  EXPECT_GT(title_ink, 60);
  // Tick labels under the plot area and left of it.
  EXPECT_GT(count_dark(one, 60, 340, 640, 370), 60);
  EXPECT_GT(count_dark(one, 0, 40, 70, 340), 60);
  Chart untitled = chart;
  untitled.title.clear();
  EXPECT_EQ(count_dark(render_chart(untitled, font), 200, 0, 440, 32), 0);
  // One series: no legend, nothing right of the last x tick label. Two: a legend
  // at the right with both series' swatches and names.
  EXPECT_EQ(count_dark(one, 624, 0, 640, 400), 0);
  EXPECT_EQ(count_colour(one, red, 614, 0, 640, 400), 0);
  Series flat{.name = "a flat line at 50",
              .x = {0, 10},
              .y = {50, 50},
              .colour = green,
              .line_width = 2.0f,
              .marker_radius = 4};
  chart.series.push_back(flat);
  const ImageRgb two = render_chart(chart, font);
  EXPECT_GT(count_colour(two, red, 470, 40, 640, 120), 20);  // the legend's swatches
  EXPECT_GT(count_colour(two, green, 470, 40, 640, 120), 20);
  EXPECT_GT(count_dark(two, 512, 40, 640, 120), 100);  // and the names beside them
  EXPECT_EQ(count_colour(one, green, 470, 40, 640, 120), 0);
  // Log scale: renders, and refuses a chart with no positive value.
  chart.log_y = true;
  EXPECT_GT(count_colour(render_chart(chart, font), red), 200);
  Chart negative{.title = "none positive", .log_y = true};
  negative.series.push_back(Series{.name = "n", .x = {0, 1}, .y = {-1, -2}});
  EXPECT_NE(error_of([&] { render_chart(negative, font); }).find("no finite point"),
            std::string::npos);
  // Through the PNG writer and back: the same pixels.
  const fs::path png = test::temp_dir() / "chart.png";
  write_png_rgb(png, one);
  EXPECT_EQ(read_png_rgb(png).pixels, one.pixels);
}

TEST(PlotChart, HeatMapShadesCellsAndWritesText) {
  const Font font(find_font());
  HeatMap map;
  map.title = "two by two";
  map.x_label = "predicted";
  map.y_label = "true";
  map.row_names = {"alpha", "beta"};
  map.column_names = {"alpha", "beta"};
  map.shade = {{1.0, 0.0}, {NAN, 0.5}};
  map.text = {{"100%\n7", ""}, {"", "50%"}};
  const ImageRgb image = render_heat_map(map, font);
  EXPECT_GT(image.width, 2 * map.cell);
  EXPECT_GT(image.height, 2 * map.cell);
  // The full-shade cell in dark blue (minus its white text), the empty one almost white, the NaN
  // one grey.
  EXPECT_GT(count_colour(image, Rgb{8, 48, 107}), map.cell * map.cell / 2);
  EXPECT_GT(count_colour(image, Rgb{247, 251, 255}), map.cell * map.cell * 3 / 4);
  EXPECT_GT(count_colour(image, Rgb{235, 235, 235}), map.cell * map.cell * 3 / 4);
  map.shade[1].pop_back();
  EXPECT_NE(error_of([&] { render_heat_map(map, font); }).find("row 1 has 1 shades"),
            std::string::npos);
}
