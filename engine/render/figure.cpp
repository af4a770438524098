#include "engine/render/figure.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "core/error.hpp"

namespace pillarseg {

namespace {

constexpr Rgb kText{30, 30, 30};
constexpr Rgb kSwatchFrame{150, 150, 150};
constexpr int kTitlePixels = 20;   // text sizes, em pixels
constexpr int kLegendPixels = 17;
constexpr int kSwatch = 18;        // a swatch's side
constexpr int kPanelGap = 10;      // under a panel
constexpr int kBarHeight = 8;

void fill(ImageRgb& image, const PixelBox& box, Rgb colour) {
  for (int y = std::max(0, box.y); y < std::min(image.height, box.y + box.height); ++y)
    for (int x = std::max(0, box.x); x < std::min(image.width, box.x + box.width); ++x) {
      uint8_t* p = image.at(x, y);
      p[0] = colour.r, p[1] = colour.g, p[2] = colour.b;
    }
}

// Text whose line (ascender to descender) is centred on y.
void draw_centred_on_line(const Font& font, ImageRgb& image, int x, int y, const std::string& text,
                          int pixels) {
  font.draw(image, x, y + (font.ascender(pixels) - font.descender(pixels)) / 2, text, pixels, kText);
}

}  // namespace

int figure_scale(int grid_width) {
  PS_CHECK(grid_width > 0, "figure_scale: a grid {} cells wide", grid_width);
  return std::max(1, (kFigureMinPanelWidth + grid_width - 1) / grid_width);
}

double scale_bar_metres(double panel_metres) {
  PS_CHECK(panel_metres > 0 && std::isfinite(panel_metres), "scale_bar_metres: a panel {} m wide", panel_metres);
  const double longest = panel_metres / 4;
  if (longest >= 10) return 10;
  const double decade = std::pow(10.0, std::floor(std::log10(longest)));
  for (const double factor : {5.0, 2.0, 1.0})
    if (factor * decade <= longest * (1 + 1e-9)) return factor * decade;
  return decade;
}

ImageRgb upscale(const ImageRgb& image, int factor) {
  PS_CHECK(factor >= 1, "upscale: factor {}, expected at least 1", factor);
  ImageRgb out(image.width * factor, image.height * factor);
  for (int y = 0; y < out.height; ++y)
    for (int x = 0; x < out.width; ++x) std::copy_n(image.at(x / factor, y / factor), 3, out.at(x, y));
  return out;
}

Figure compose_figure(const std::vector<TitledPanel>& panels, const ClassTable& classes, double cell_metres,
                      const Font& font) {
  PS_CHECK(!panels.empty(), "compose_figure: no panels");
  PS_CHECK(cell_metres > 0, "compose_figure: cell size {} m, expected > 0", cell_metres);
  const int cells_wide = panels[0].image.width, cells_high = panels[0].image.height;
  for (const TitledPanel& p : panels)
    PS_CHECK(p.image.width == cells_wide && p.image.height == cells_high,
             "compose_figure: panel '{}' is {}x{}, the first {}x{}", p.title, p.image.width, p.image.height,
             cells_wide, cells_high);
  Figure figure;
  figure.scale = figure_scale(cells_wide);
  const int panel_width = cells_wide * figure.scale, panel_height = cells_high * figure.scale;
  const int title_line = font.ascender(kTitlePixels) + font.descender(kTitlePixels) + 6;
  const int legend_line = std::max(kSwatch, font.ascender(kLegendPixels) + font.descender(kLegendPixels)) + 8;

  // Layout, top to bottom: titles and panels, the legend, the scale bar.
  int y = kFigureMargin;
  std::vector<int> title_tops;
  for (size_t i = 0; i < panels.size(); ++i) {
    title_tops.push_back(y);
    y += title_line;
    figure.panels.push_back({kFigureMargin, y, panel_width, panel_height});
    y += panel_height + kPanelGap;
  }
  int name_width = 0;
  for (int k = 1; k <= kNumClasses; ++k) name_width = std::max(name_width, font.text_width(classes.name(k), kLegendPixels));
  const int entry_width = kSwatch + 8 + name_width + 24;
  const int columns = std::clamp(panel_width / entry_width, 1, kNumClasses);
  for (int k = 1; k <= kNumClasses; ++k) {
    const int column = (k - 1) % columns, row = (k - 1) / columns;
    figure.swatches.push_back({kFigureMargin + column * entry_width,
                               y + row * legend_line + (legend_line - kSwatch) / 2, kSwatch, kSwatch});
  }
  y += (kNumClasses + columns - 1) / columns * legend_line + 6;
  figure.scale_bar_metres = scale_bar_metres(cells_wide * cell_metres);
  const int bar_length = static_cast<int>(std::lround(figure.scale_bar_metres / cell_metres * figure.scale));
  figure.scale_bar = {kFigureMargin, y + (legend_line - kBarHeight) / 2, bar_length, kBarHeight};
  y += legend_line + kFigureMargin;

  figure.image = ImageRgb(panel_width + 2 * kFigureMargin, y);
  ImageRgb& image = figure.image;
  std::fill(image.pixels.begin(), image.pixels.end(), uint8_t{255});
  for (size_t i = 0; i < panels.size(); ++i) {
    draw_centred_on_line(font, image, kFigureMargin, title_tops[i] + title_line / 2, panels[i].title, kTitlePixels);
    const ImageRgb scaled = upscale(panels[i].image, figure.scale);
    const PixelBox& box = figure.panels[i];
    for (int row = 0; row < box.height; ++row)
      std::copy_n(scaled.at(0, row), 3 * box.width, image.at(box.x, box.y + row));
  }
  for (int k = 1; k <= kNumClasses; ++k) {
    const PixelBox& s = figure.swatches[static_cast<size_t>(k - 1)];
    fill(image, {s.x - 1, s.y - 1, s.width + 2, s.height + 2}, kSwatchFrame);
    fill(image, s, classes.color(k));
    draw_centred_on_line(font, image, s.x + kSwatch + 8, s.y + kSwatch / 2, classes.name(k), kLegendPixels);
  }
  fill(image, figure.scale_bar, kText);
  draw_centred_on_line(font, image, figure.scale_bar.x + bar_length + 12, figure.scale_bar.y + kBarHeight / 2,
                       fmt::format("{:g} m   (cells of {:g} m, {} pixel{} a cell)", figure.scale_bar_metres,
                                   cell_metres, figure.scale, figure.scale == 1 ? "" : "s"),
                       kLegendPixels);
  return figure;
}

}  // namespace pillarseg
